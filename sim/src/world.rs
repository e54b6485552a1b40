//! The simulated 3D scene: a textured ground plane with buildings and
//! smaller objects (vehicles, containers, kiosks) within about 100 m of home.
//!
//! # World frame
//!
//! The world frame **is the local NED frame at home**: x north, y east,
//! z down, in metres, origin at the home position on the ground. The
//! documented fixed transform between render-world coordinates and NED is
//! therefore the identity. The ground is the plane z = 0; buildings stand on
//! it and extend to negative z (a 20 m tall building spans z ∈ [-20, 0]).
//! A camera flying at 30 m altitude has z = -30. Camera poses are
//! `world_from_cam` with camera axes x right, y down, z forward.
//!
//! # Texture
//!
//! Everything the camera can see is textured procedurally, and no tile
//! repeats inside a view: the ground texture covers 256 m x 256 m at
//! 6.25 cm/texel (multi-octave value noise, a "dead leaves" patchwork of
//! shapes, roads with lane markings, crosswalks, sidewalks, parking lots and
//! baked sun shadows of the buildings), a coarse texture covers the land
//! beyond, facades sample a 128 m facade atlas (window grids in several
//! styles, floor bands, grime) at a per-face offset, roofs a roof atlas (AC
//! units, pipes, vents). For close views two detail layers (8 m and
//! 8·φ m, rotated by 35°, so their sum never repeats) add texture down to
//! 8 mm; they fade out through the mip chain when the camera is far.

use nalgebra::{Point3, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use crate::texture::{Canvas, MipTexture};

/// Errors of the world.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum WorldError {
    /// A world parameter is out of range.
    #[error("invalid world parameter {name}: {value}")]
    InvalidParam {
        /// Parameter name.
        name: &'static str,
        /// Its value.
        value: f64,
    },
    /// The world kind's name is not known.
    #[error("unknown world {name:?}: use town, grass, carpark, trees, water, traffic or aliasing")]
    UnknownKind {
        /// The name given.
        name: String,
    },
}

/// The kind of terrain a world is, selectable by name (`--world NAME`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum WorldKind {
    /// `town`: buildings, roads, parked cars and rich texture everywhere
    /// (the simulator's original world).
    #[default]
    Town,
    /// `grass`: open grass with mowing stripes, a dirt path and little
    /// else: low texture.
    Grass,
    /// `carpark`: a large car park with identical stall markings and
    /// identical cars (perceptual aliasing for bag-of-words).
    Carpark,
    /// `trees`: an orchard-like wood of identical trees with repetitive
    /// foliage over a repetitive forest floor.
    Trees,
    /// `water`: two lakes beside a strip of land with buildings: a rippled,
    /// reflecting surface with no stable features.
    Water,
    /// `traffic`: the town with its cars driving along the roads.
    Traffic,
    /// `aliasing`: a grid of identical buildings around a car park of
    /// identical cars, built to fool bag-of-words place recognition.
    Aliasing,
}

impl WorldKind {
    /// Every kind, in documentation order.
    pub const ALL: [WorldKind; 7] = [
        WorldKind::Town,
        WorldKind::Grass,
        WorldKind::Carpark,
        WorldKind::Trees,
        WorldKind::Water,
        WorldKind::Traffic,
        WorldKind::Aliasing,
    ];

    /// The kind's name.
    pub fn name(self) -> &'static str {
        match self {
            WorldKind::Town => "town",
            WorldKind::Grass => "grass",
            WorldKind::Carpark => "carpark",
            WorldKind::Trees => "trees",
            WorldKind::Water => "water",
            WorldKind::Traffic => "traffic",
            WorldKind::Aliasing => "aliasing",
        }
    }
}

impl std::fmt::Display for WorldKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for WorldKind {
    type Err = WorldError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        WorldKind::ALL
            .into_iter()
            .find(|k| k.name() == s)
            .ok_or_else(|| WorldError::UnknownKind {
                name: s.to_string(),
            })
    }
}

/// Every tunable number of the world generator.
#[derive(Debug, Clone, PartialEq)]
pub struct WorldParams {
    /// The kind of terrain (the layout and ground texture follow it).
    pub kind: WorldKind,
    /// Texels across the ground texture (power of two).
    pub ground_texture_size: usize,
    /// Metres across the ground texture, centred on home.
    pub ground_extent_m: f64,
    /// Texels across the texture of the land beyond.
    pub far_texture_size: usize,
    /// Metres across the texture of the land beyond.
    pub far_extent_m: f64,
    /// Texels across the facade atlas.
    pub facade_texture_size: usize,
    /// Metres across the facade atlas.
    pub facade_extent_m: f64,
    /// Texels across the roof atlas.
    pub roof_texture_size: usize,
    /// Metres across the roof atlas.
    pub roof_extent_m: f64,
    /// Texels across each close-up detail texture.
    pub detail_texture_size: usize,
    /// Metres across the first detail layer (the second is φ times larger).
    pub detail_extent_m: f64,
    /// Number of buildings to place.
    pub building_count: usize,
    /// Number of small objects (cars, containers, kiosks) to place.
    pub object_count: usize,
    /// Buildings and objects stay within this radius of home, metres.
    pub scene_radius_m: f64,
    /// No building within this radius of home (the take-off area), metres.
    pub clear_radius_m: f64,
    /// Sun azimuth, degrees clockwise from north.
    pub sun_azimuth_deg: f64,
    /// Sun elevation above the horizon, degrees.
    pub sun_elevation_deg: f64,
    /// Brightness of a shadowed ground texel relative to a lit one.
    pub shadow_factor: f32,
    /// Share of the light that is ambient (not from the sun).
    pub ambient: f32,
    /// Gain of the first detail layer.
    pub detail_gain_a: f32,
    /// Gain of the second detail layer.
    pub detail_gain_b: f32,
    /// Gain of the close-up layer (the second detail texture at a quarter
    /// scale), which fades in when the first layer is magnified.
    pub detail_gain_close: f32,
    /// Mip level of the first detail layer below which (magnified) the
    /// close-up layer starts to fade in.
    pub close_detail_start_lod: f32,
    /// Detail layers start fading out at this mip level of their own...
    pub detail_fade_start_lod: f32,
    /// ...and are gone (not sampled) from this one: their features are
    /// then smaller than a pixel and the base textures carry the view.
    pub detail_fade_end_lod: f32,
}

impl Default for WorldParams {
    fn default() -> Self {
        Self {
            kind: WorldKind::Town,
            ground_texture_size: 4096,
            ground_extent_m: 256.0,
            far_texture_size: 1024,
            far_extent_m: 4096.0,
            facade_texture_size: 2048,
            facade_extent_m: 128.0,
            roof_texture_size: 1024,
            roof_extent_m: 51.2,
            detail_texture_size: 1024,
            detail_extent_m: 8.0,
            building_count: 40,
            object_count: 70,
            scene_radius_m: 100.0,
            clear_radius_m: 15.0,
            sun_azimuth_deg: 150.0,
            sun_elevation_deg: 50.0,
            shadow_factor: 0.55,
            ambient: 0.45,
            detail_gain_a: 0.55,
            detail_gain_b: 0.4,
            detail_gain_close: 0.45,
            close_detail_start_lod: -1.0,
            detail_fade_start_lod: 2.5,
            detail_fade_end_lod: 3.5,
        }
    }
}

impl WorldParams {
    /// A quarter-resolution world for quick tests (same layout rules).
    pub fn small() -> Self {
        Self {
            ground_texture_size: 1024,
            far_texture_size: 256,
            facade_texture_size: 512,
            roof_texture_size: 256,
            detail_texture_size: 256,
            ..Self::default()
        }
    }

    /// The same layout with 64-texel textures: for tests about geometry
    /// and paths, where texture detail does not matter.
    pub fn tiny() -> Self {
        Self {
            ground_texture_size: 64,
            far_texture_size: 64,
            facade_texture_size: 64,
            roof_texture_size: 64,
            detail_texture_size: 64,
            ..Self::default()
        }
    }

    fn validate(&self) -> Result<(), WorldError> {
        let sizes = [
            ("ground_texture_size", self.ground_texture_size),
            ("far_texture_size", self.far_texture_size),
            ("facade_texture_size", self.facade_texture_size),
            ("roof_texture_size", self.roof_texture_size),
            ("detail_texture_size", self.detail_texture_size),
        ];
        for (name, s) in sizes {
            if !(4..=16384).contains(&s) || !s.is_power_of_two() {
                return Err(WorldError::InvalidParam {
                    name,
                    value: s as f64,
                });
            }
        }
        let extents = [
            ("ground_extent_m", self.ground_extent_m),
            ("far_extent_m", self.far_extent_m),
            ("facade_extent_m", self.facade_extent_m),
            ("roof_extent_m", self.roof_extent_m),
            ("detail_extent_m", self.detail_extent_m),
            ("scene_radius_m", self.scene_radius_m),
        ];
        for (name, e) in extents {
            if !(e.is_finite() && e > 0.0) {
                return Err(WorldError::InvalidParam { name, value: e });
            }
        }
        if !(self.sun_elevation_deg > 1.0 && self.sun_elevation_deg <= 90.0) {
            return Err(WorldError::InvalidParam {
                name: "sun_elevation_deg",
                value: self.sun_elevation_deg,
            });
        }
        Ok(())
    }
}

/// What a box in the scene is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BoxKind {
    /// A building with windows and a roof.
    Building,
    /// A car on a road.
    Car,
    /// A shipping container.
    Container,
    /// A kiosk or shed.
    Kiosk,
    /// A tree: a crown of foliage (a box above the ground) or its trunk.
    Tree,
}

/// An axis-aligned box standing on the ground (NED, metres).
#[derive(Debug, Clone, PartialEq)]
pub struct SceneBox {
    /// Minimum corner (`min.z` is minus the height).
    pub min: Vector3<f64>,
    /// Maximum corner (`max.z` is 0: the box stands on the ground).
    pub max: Vector3<f64>,
    /// What it is.
    pub kind: BoxKind,
    /// Offset into the facade atlas, metres (u, v).
    pub facade_offset: [f32; 2],
    /// Offset into the roof atlas, metres.
    pub roof_offset: [f32; 2],
    /// Facade coordinates are multiplied by this (small objects look finer).
    pub texture_scale: f32,
    /// Brightness multiplier of the whole box.
    pub albedo: f32,
    /// Texture coordinates relative to the box's own corner, so boxes of
    /// the same size and offsets look identical wherever they stand.
    pub local_texture: bool,
}

impl SceneBox {
    /// Height above the ground, metres.
    pub fn height(&self) -> f64 {
        -self.min.z
    }
}

/// A face of a box, by outward normal.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Face {
    /// Normal -x (south wall).
    NegX,
    /// Normal +x (north wall).
    PosX,
    /// Normal -y (west wall).
    NegY,
    /// Normal +y (east wall).
    PosY,
    /// Normal -z (the roof, facing up).
    Top,
    /// Normal +z (the underside, never seen from above ground).
    Bottom,
}

impl Face {
    /// Index 0..6 in declaration order.
    pub fn index(self) -> usize {
        self as usize
    }

    /// Outward unit normal in the world (NED) frame.
    pub fn normal(self) -> Vector3<f64> {
        match self {
            Face::NegX => -Vector3::x(),
            Face::PosX => Vector3::x(),
            Face::NegY => -Vector3::y(),
            Face::PosY => Vector3::y(),
            Face::Top => -Vector3::z(),
            Face::Bottom => Vector3::z(),
        }
    }

    pub(crate) fn from_axis(axis: usize, ray_dir_positive: bool) -> Face {
        // Entering through the face whose normal opposes the ray.
        match (axis, ray_dir_positive) {
            (0, true) => Face::NegX,
            (0, false) => Face::PosX,
            (1, true) => Face::NegY,
            (1, false) => Face::PosY,
            (_, true) => Face::Top,
            (_, false) => Face::Bottom,
        }
    }
}

/// What a ray hit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Surface {
    /// The ground plane z = 0.
    Ground,
    /// A face of box `index`.
    Box {
        /// Index into [`World::boxes`].
        index: usize,
        /// The face.
        face: Face,
    },
}

/// A ray hit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Distance along the (unit) ray, metres.
    pub t: f64,
    /// The hit point in the world frame.
    pub p_world: Point3<f64>,
    /// What was hit.
    pub surface: Surface,
}

/// The generated textures with their metric scales.
#[derive(Debug, Clone)]
pub(crate) struct Textures {
    pub ground: MipTexture,
    pub ground_inv_texel: f32,
    pub ground_half_extent: f32,
    pub far: MipTexture,
    pub far_inv_texel: f32,
    pub facade: MipTexture,
    pub facade_inv_texel: f32,
    pub roof: MipTexture,
    pub roof_inv_texel: f32,
    pub detail_a: MipTexture,
    pub detail_a_inv_texel: f32,
    pub detail_a_log2_inv_texel: f32,
    pub detail_b: MipTexture,
    pub detail_b_inv_texel: f32,
    pub detail_b_log2_inv_texel: f32,
    /// cos, sin of the second detail layer's rotation.
    pub detail_b_rot: (f32, f32),
    /// cos, sin of the close-up layer's rotation.
    pub detail_close_rot: (f32, f32),
    /// Foliage of the trees (only in the `trees` world).
    pub foliage: Option<MipTexture>,
    pub foliage_inv_texel: f32,
}

/// The scene: boxes on a ground plane, with their textures.
#[derive(Debug, Clone)]
pub struct World {
    /// The seed it was generated from.
    pub seed: u64,
    /// The parameters it was generated with.
    pub params: WorldParams,
    /// Buildings and objects.
    pub boxes: Vec<SceneBox>,
    /// Roads: (is_along_x, centre coordinate across, width), metres.
    pub roads: Vec<Road>,
    pub(crate) textures: Textures,
    /// Unit vector towards the sun (NED).
    pub sun_dir: Vector3<f64>,
    /// Lighting factor per face (index by [`Face::index`]), ground = 1.
    pub(crate) face_light: [f32; 6],
    /// Boxes that drive (cars on roads): they stand at [`World::boxes_at`].
    pub movers: Vec<Mover>,
    /// Open water (lakes), where the ground is a rippled mirror.
    pub water: Vec<WaterBody>,
}

/// A box that drives back and forth along a road: its centre moves along
/// x (or y) at a constant speed and wraps around within `[lo, hi)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Mover {
    /// Index into [`World::boxes`] (the box's position at time 0).
    pub index: usize,
    /// True if it drives along x (north-south).
    pub along_x: bool,
    /// Signed speed, m/s.
    pub speed_m_s: f64,
    /// The stretch of road it wraps around on (along coordinate), metres.
    pub lo: f64,
    /// End of that stretch, metres.
    pub hi: f64,
}

/// A rectangle of open water on the ground (NED metres).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WaterBody {
    /// South-west corner (x, y).
    pub min: [f64; 2],
    /// North-east corner (x, y).
    pub max: [f64; 2],
}

/// A straight road across the scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Road {
    /// True if the road runs along x (north-south), at constant y.
    pub along_x: bool,
    /// The constant coordinate of its centre line (y if `along_x`, else x).
    pub centre: f64,
    /// Width, metres.
    pub width: f64,
}

const PHI: f64 = 1.618_033_988_749_895;

impl World {
    /// Generates the default world for a seed.
    pub fn generate(seed: u64) -> World {
        // The default parameters are valid, so this cannot fail.
        match Self::generate_with(seed, &WorldParams::default()) {
            Ok(w) => w,
            Err(e) => unreachable!("default world params are valid: {e}"),
        }
    }

    /// Generates a world with explicit parameters.
    pub fn generate_with(seed: u64, params: &WorldParams) -> Result<World, WorldError> {
        params.validate()?;
        let mut params = params.clone();
        params.kind.adjust(&mut params);
        let params = &params;
        let mut rng = StdRng::seed_from_u64(seed);
        let (roads, boxes, movers, water) = layout_kind(&mut rng, seed, params);
        let el = params.sun_elevation_deg.to_radians();
        let az = params.sun_azimuth_deg.to_radians();
        let sun_dir = Vector3::new(el.cos() * az.cos(), el.cos() * az.sin(), -el.sin());
        let amb = params.ambient;
        let ground_light = amb + (1.0 - amb) * el.sin() as f32;
        let mut face_light = [0.0f32; 6];
        for face in [
            Face::NegX,
            Face::PosX,
            Face::NegY,
            Face::PosY,
            Face::Top,
            Face::Bottom,
        ] {
            let lambert = face.normal().dot(&sun_dir).max(0.0) as f32;
            face_light[face.index()] = (amb + (1.0 - amb) * lambert) / ground_light;
        }
        let textures = make_textures(seed, params, &roads, &boxes, &sun_dir);
        Ok(World {
            seed,
            params: params.clone(),
            boxes,
            roads,
            textures,
            sun_dir,
            face_light,
            movers,
            water,
        })
    }

    /// True when nothing in the world changes with time (no moving
    /// objects, no water): a frame depends only on the camera pose.
    pub fn is_static(&self) -> bool {
        self.movers.is_empty() && self.water.is_empty()
    }

    /// The boxes where they stand at scene time `t_s` (borrowed when
    /// nothing moves).
    pub fn boxes_at(&self, t_s: f64) -> std::borrow::Cow<'_, [SceneBox]> {
        if self.movers.is_empty() {
            return std::borrow::Cow::Borrowed(&self.boxes);
        }
        let mut boxes = self.boxes.clone();
        for m in &self.movers {
            let Some(b) = boxes.get_mut(m.index) else {
                continue;
            };
            let axis = if m.along_x { 0 } else { 1 };
            let centre = 0.5 * (b.min[axis] + b.max[axis]);
            let span = (m.hi - m.lo).max(1e-6);
            let moved = m.lo + (centre - m.lo + m.speed_m_s * t_s).rem_euclid(span);
            let shift = moved - centre;
            b.min[axis] += shift;
            b.max[axis] += shift;
        }
        std::borrow::Cow::Owned(boxes)
    }

    /// True if ground point (x, y) is open water.
    #[inline(always)]
    pub(crate) fn water_at(&self, x: f32, y: f32) -> bool {
        let (x, y) = (x as f64, y as f64);
        self.water
            .iter()
            .any(|w| x >= w.min[0] && x <= w.max[0] && y >= w.min[1] && y <= w.max[1])
    }

    /// Brightness of the water body (what light comes up from below the
    /// surface) at (x, y): dark, with slow turbid swirls that drift.
    pub(crate) fn water_body_value(&self, x: f32, y: f32, t: f32) -> f32 {
        let s = &self.textures;
        let u = (x + 0.31 * t) * s.far_inv_texel * 4.0;
        let v = (y - 0.23 * t) * s.far_inv_texel * 4.0;
        let swirl = s.far.sample_lod(u, v, 2.0) - s.far.mean();
        (38.0 + 0.15 * swirl).max(5.0)
    }

    /// Height of the tallest box covering ground point (x, y), 0 if none.
    pub fn height_at(&self, x: f64, y: f64) -> f64 {
        self.max_height_near(x, y, 0.0)
    }

    /// Height of the tallest box within `radius` of ground point (x, y).
    pub fn max_height_near(&self, x: f64, y: f64, radius: f64) -> f64 {
        self.boxes
            .iter()
            .filter(|b| {
                x >= b.min.x - radius
                    && x <= b.max.x + radius
                    && y >= b.min.y - radius
                    && y <= b.max.y + radius
            })
            .map(SceneBox::height)
            .fold(0.0, f64::max)
    }

    /// Casts a ray (any non-zero `dir`) and returns the first hit within
    /// `max_t` metres, in double precision.
    pub fn ray_cast(&self, origin: &Point3<f64>, dir: &Vector3<f64>, max_t: f64) -> Option<Hit> {
        let n = dir.norm();
        if !(n > 0.0 && n.is_finite()) {
            return None;
        }
        let d = dir / n;
        let mut best_t = max_t;
        let mut best = None;
        if d.z > 1e-12 && origin.z < 0.0 {
            let t = -origin.z / d.z;
            if t < best_t {
                best_t = t;
                best = Some(Surface::Ground);
            }
        }
        for (index, b) in self.boxes.iter().enumerate() {
            let mut t0 = 0.0f64;
            let mut t1 = best_t;
            let mut axis = 0usize;
            let mut ok = true;
            for a in 0..3 {
                let inv = 1.0 / d[a];
                let mut ta = (b.min[a] - origin[a]) * inv;
                let mut tb = (b.max[a] - origin[a]) * inv;
                if ta > tb {
                    std::mem::swap(&mut ta, &mut tb);
                }
                if ta > t0 {
                    t0 = ta;
                    axis = a;
                }
                t1 = t1.min(tb);
                if t0 > t1 {
                    ok = false;
                    break;
                }
            }
            if ok && t0 > 0.0 && t0 < best_t {
                best_t = t0;
                best = Some(Surface::Box {
                    index,
                    face: Face::from_axis(axis, d[axis] > 0.0),
                });
            }
        }
        best.map(|surface| Hit {
            t: best_t,
            p_world: origin + d * best_t,
            surface,
        })
    }

    /// Ground brightness (0..255 scale, before haze) at (x, y) for a pixel
    /// footprint of `footprint_m` metres (log2 given as `lod_m`).
    #[inline(always)]
    pub(crate) fn ground_value(&self, x: f32, y: f32, lod_m: f32) -> f32 {
        let tx = &self.textures;
        let h = tx.ground_half_extent;
        let base = if x > -h && x < h && y > -h && y < h {
            let s = tx.ground_inv_texel;
            sample_at(&tx.ground, (x + h) * s, (y + h) * s, lod_m, s)
        } else {
            let s = tx.far_inv_texel;
            sample_at(&tx.far, x * s, y * s, lod_m, s)
        };
        base + self.detail(x, y, lod_m)
    }

    /// Close-up detail offset (zero mean) at surface coordinates (u, v).
    #[inline(always)]
    pub(crate) fn detail(&self, u: f32, v: f32, lod_m: f32) -> f32 {
        let tx = &self.textures;
        let fade_end = self.params.detail_fade_end_lod;
        let fade_k = 1.0 / (fade_end - self.params.detail_fade_start_lod).max(1e-3);
        let mut out = 0.0;
        let lod_a = lod_m + tx.detail_a_log2_inv_texel;
        if lod_a < fade_end {
            let sa = tx.detail_a_inv_texel;
            let w = ((fade_end - lod_a) * fade_k).min(1.0) * self.params.detail_gain_a;
            let lod = lod_a.max(0.0);
            out += (tx.detail_a.sample_lod(u * sa, v * sa, lod) - tx.detail_a.mean()) * w;
            let lod_b = lod_m + tx.detail_b_log2_inv_texel;
            if lod_b < fade_end {
                let sb = tx.detail_b_inv_texel;
                let w = ((fade_end - lod_b) * fade_k).min(1.0) * self.params.detail_gain_b;
                let (c, s) = tx.detail_b_rot;
                let ub = (c * u - s * v) * sb;
                let vb = (s * u + c * v) * sb;
                out += (tx.detail_b.sample_lod(ub, vb, lod_b.max(0.0)) - tx.detail_b.mean()) * w;
            }
            // Very close (the first layer magnified): the second layer's
            // texture again at a quarter of its scale, turned another way,
            // fading in as the first one blurs.
            let close_start = self.params.close_detail_start_lod;
            if lod_a < close_start {
                let w = ((close_start - lod_a) * fade_k).min(1.0) * self.params.detail_gain_close;
                let sc = tx.detail_b_inv_texel * 4.0;
                let (c, s) = tx.detail_close_rot;
                let uc = (c * u - s * v) * sc;
                let vc = (s * u + c * v) * sc;
                let lod_c = (lod_m + tx.detail_b_log2_inv_texel + 2.0).max(0.0);
                out += (tx.detail_b.sample_lod(uc, vc, lod_c) - tx.detail_b.mean()) * w;
            }
        }
        out
    }

    /// Brightness of box `b` at point `p` on `face`.
    #[inline(always)]
    pub(crate) fn box_value(&self, b: &SceneBox, face: Face, p: [f32; 3], lod_m: f32) -> f32 {
        let tx = &self.textures;
        let light = self.face_light[face.index()];
        let p = if b.local_texture {
            [
                p[0] - b.min.x as f32,
                p[1] - b.min.y as f32,
                p[2] - b.max.z as f32,
            ]
        } else {
            p
        };
        if b.kind == BoxKind::Tree
            && let Some(foliage) = &tx.foliage
        {
            // Foliage on every face, in the box's own coordinates.
            let (u, w) = match face {
                Face::Top | Face::Bottom => (p[0], p[1]),
                Face::NegX | Face::PosX => (p[1], p[2]),
                _ => (p[0], p[2]),
            };
            let s = tx.foliage_inv_texel;
            return sample_at(foliage, u * s, w * s, lod_m, s) * light * b.albedo;
        }
        let v = match face {
            Face::Top | Face::Bottom => {
                let s = tx.roof_inv_texel;
                let u = p[0] + b.roof_offset[0];
                let w = p[1] + b.roof_offset[1];
                sample_at(&tx.roof, u * s, w * s, lod_m, s) + self.detail(u, w, lod_m)
            }
            _ => {
                // Horizontal coordinate along the wall, vertical = height.
                let along = match face {
                    Face::NegX => -p[1],
                    Face::PosX => p[1],
                    Face::NegY => p[0],
                    _ => -p[0],
                };
                let k = b.texture_scale;
                let u = along * k + b.facade_offset[0] + face.index() as f32 * 23.7;
                let w = -p[2] * k + b.facade_offset[1];
                let s = tx.facade_inv_texel;
                let lod = lod_m + crate::texture::fast_log2(k.max(1e-3));
                sample_at(&tx.facade, u * s, w * s, lod, s) + self.detail(u, w, lod)
            }
        };
        v * light * b.albedo
    }

    /// Paints a disc of brightness `value` and radius `radius_m` centred at
    /// ground point (x, y), on a square of `background_value` with half size
    /// `background_half_m` (a calibration marker for tests).
    pub fn paint_ground_marker(
        &mut self,
        x: f64,
        y: f64,
        radius_m: f64,
        value: f32,
        background_half_m: f64,
        background_value: f32,
    ) {
        let tx = &mut self.textures;
        let mut canvas = tx.ground.level0_canvas();
        let s = tx.ground_inv_texel as f64;
        let h = tx.ground_half_extent as f64;
        let c = (((x + h) * s) as f32, ((y + h) * s) as f32);
        let bh = (background_half_m * s) as f32;
        canvas.rect(c, (bh, bh), 0.0, background_value, 1.0);
        canvas.disc(c, (radius_m * s) as f32, value, 1.0);
        tx.ground = canvas.into_mip();
    }
}

/// The water surface's unit normal (pointing up, -z) at (x, y) and scene
/// time `t`: a sum of gravity waves (deep-water dispersion, angular
/// frequency sqrt(g k)) from several directions, so the pattern never repeats
/// in time or space over a view. The slope's rms, 0.15, is Cox and Munk's
/// (1954) for a 4 m/s wind (slope variance 0.003 + 0.00512 U).
#[inline(always)]
pub(crate) fn water_normal(x: f32, y: f32, t: f32) -> [f32; 3] {
    // (direction (unit), wavenumber rad/m, slope amplitude, phase).
    const WAVES: [([f32; 2], f32, f32, f32); 5] = [
        ([0.96, 0.28], 2.1, 0.14, 0.3),
        ([0.5, -0.87], 3.4, 0.11, 1.7),
        ([-0.71, 0.71], 5.3, 0.09, 4.1),
        ([0.17, 0.98], 8.9, 0.06, 2.6),
        ([-0.94, -0.34], 13.7, 0.05, 5.5),
    ];
    let (mut gx, mut gy) = (0.0f32, 0.0f32);
    for (dir, k, slope, phase) in WAVES {
        let omega = (9.81 * k).sqrt();
        let arg = k * (dir[0] * x + dir[1] * y) - omega * t + phase;
        let c = arg.cos() * slope;
        gx += c * dir[0];
        gy += c * dir[1];
    }
    let n = (gx * gx + gy * gy + 1.0).sqrt();
    [-gx / n, -gy / n, -1.0 / n]
}

impl World {
    /// Paints an axis-aligned rectangle of brightness `value` centred at
    /// ground point (x, y) with half sizes `half_x`, `half_y` metres (a
    /// calibration target for tests).
    pub fn paint_ground_rect(&mut self, x: f64, y: f64, half_x: f64, half_y: f64, value: f32) {
        let tx = &mut self.textures;
        let mut canvas = tx.ground.level0_canvas();
        let s = tx.ground_inv_texel as f64;
        let h = tx.ground_half_extent as f64;
        let c = (((x + h) * s) as f32, ((y + h) * s) as f32);
        canvas.rect(
            c,
            ((half_x * s) as f32, (half_y * s) as f32),
            0.0,
            value,
            1.0,
        );
        tx.ground = canvas.into_mip();
    }
}

/// Samples a texture at texel coordinates for a pixel footprint whose log2
/// in metres is `lod_m`, with `inv_texel` texels per metre.
#[inline(always)]
fn sample_at(t: &MipTexture, u: f32, v: f32, lod_m: f32, inv_texel: f32) -> f32 {
    match t.lod_from(lod_m + crate::texture::fast_log2(inv_texel)) {
        Some(lod) => t.sample_lod(u, v, lod),
        None => t.mean(),
    }
}

fn layout_roads(rng: &mut StdRng, p: &WorldParams) -> Vec<Road> {
    let mut roads = Vec::new();
    let limit = p.ground_extent_m * 0.5 - 5.0;
    for along_x in [true, false] {
        let mut c = -limit + rng.random_range(5.0..30.0);
        while c < limit {
            // Keep roads off home so the take-off area is open ground.
            if c.abs() > 8.0 {
                roads.push(Road {
                    along_x,
                    centre: c,
                    width: rng.random_range(7.0..11.0),
                });
            }
            c += rng.random_range(38.0..70.0);
        }
    }
    roads
}

fn overlaps_road(roads: &[Road], min: (f64, f64), max: (f64, f64), margin: f64) -> bool {
    roads.iter().any(|r| {
        let (lo, hi) = if r.along_x {
            (min.1, max.1)
        } else {
            (min.0, max.0)
        };
        hi > r.centre - r.width * 0.5 - margin && lo < r.centre + r.width * 0.5 + margin
    })
}

fn layout_boxes(rng: &mut StdRng, p: &WorldParams, roads: &[Road]) -> Vec<SceneBox> {
    let mut boxes: Vec<SceneBox> = Vec::new();
    let free = |boxes: &[SceneBox], min: (f64, f64), max: (f64, f64), margin: f64| {
        boxes.iter().all(|b| {
            max.0 + margin < b.min.x
                || min.0 - margin > b.max.x
                || max.1 + margin < b.min.y
                || min.1 - margin > b.max.y
        })
    };
    let mut attempts = 0;
    while boxes.iter().filter(|b| b.kind == BoxKind::Building).count() < p.building_count
        && attempts < 20_000
    {
        attempts += 1;
        let r = p.scene_radius_m * rng.random::<f64>().sqrt();
        let a = rng.random_range(0.0..std::f64::consts::TAU);
        let (cx, cy) = (r * a.cos(), r * a.sin());
        let w = 6.0 * (5.0f64).powf(rng.random::<f64>());
        let d = 6.0 * (5.0f64).powf(rng.random::<f64>());
        let h = 4.0 + 30.0 * rng.random::<f64>().powf(1.8);
        let min = (cx - w * 0.5, cy - d * 0.5);
        let max = (cx + w * 0.5, cy + d * 0.5);
        let near_home = min.0 < p.clear_radius_m
            && max.0 > -p.clear_radius_m
            && min.1 < p.clear_radius_m
            && max.1 > -p.clear_radius_m;
        if near_home || overlaps_road(roads, min, max, 2.0) || !free(&boxes, min, max, 3.0) {
            continue;
        }
        boxes.push(SceneBox {
            min: Vector3::new(min.0, min.1, -h),
            max: Vector3::new(max.0, max.1, 0.0),
            kind: BoxKind::Building,
            facade_offset: [
                rng.random_range(0.0..128.0),
                32.0 * rng.random_range(0..4) as f32,
            ],
            roof_offset: [rng.random_range(0.0..51.2), rng.random_range(0.0..51.2)],
            texture_scale: 1.0,
            albedo: rng.random_range(0.8..1.15),
            local_texture: false,
        });
    }
    let mut placed = 0;
    attempts = 0;
    while placed < p.object_count && attempts < 20_000 {
        attempts += 1;
        let kind = match rng.random_range(0..10) {
            0..=5 => BoxKind::Car,
            6..=7 => BoxKind::Container,
            _ => BoxKind::Kiosk,
        };
        let (mut l, mut wd, h) = match kind {
            BoxKind::Car => (
                rng.random_range(3.8..5.0),
                rng.random_range(1.7..2.0),
                rng.random_range(1.4..1.8),
            ),
            BoxKind::Container => (6.06, 2.44, 2.59),
            _ => (
                rng.random_range(2.0..4.0),
                rng.random_range(2.0..4.0),
                rng.random_range(2.3..3.2),
            ),
        };
        let (cx, cy, along_x);
        if kind == BoxKind::Car && !roads.is_empty() {
            let road = roads[rng.random_range(0..roads.len())];
            let along = rng.random_range(-p.scene_radius_m..p.scene_radius_m);
            let lane = road.width * 0.25 * if rng.random_bool(0.5) { 1.0 } else { -1.0 };
            along_x = road.along_x;
            if road.along_x {
                cx = along;
                cy = road.centre + lane;
            } else {
                cx = road.centre + lane;
                cy = along;
            }
        } else {
            let r = p.scene_radius_m * rng.random::<f64>().sqrt();
            let a = rng.random_range(0.0..std::f64::consts::TAU);
            cx = r * a.cos();
            cy = r * a.sin();
            along_x = rng.random_bool(0.5);
            if overlaps_road(roads, (cx - l, cy - l), (cx + l, cy + l), 1.0) {
                continue;
            }
        }
        if !along_x {
            std::mem::swap(&mut l, &mut wd);
        }
        let min = (cx - l * 0.5, cy - wd * 0.5);
        let max = (cx + l * 0.5, cy + wd * 0.5);
        let r = (cx * cx + cy * cy).sqrt();
        if r < p.clear_radius_m * 0.6 || r > p.scene_radius_m || !free(&boxes, min, max, 1.0) {
            continue;
        }
        boxes.push(SceneBox {
            min: Vector3::new(min.0, min.1, -h),
            max: Vector3::new(max.0, max.1, 0.0),
            kind,
            facade_offset: [rng.random_range(0.0..128.0), rng.random_range(0.0..128.0)],
            roof_offset: [rng.random_range(0.0..51.2), rng.random_range(0.0..51.2)],
            texture_scale: match kind {
                BoxKind::Car => 2.5,
                _ => 1.5,
            },
            albedo: rng.random_range(0.6..1.3),
            local_texture: false,
        });
        placed += 1;
    }
    boxes
}

/// Log-uniform sample in [lo, hi].
fn log_uniform(rng: &mut StdRng, lo: f32, hi: f32) -> f32 {
    lo * (hi / lo).powf(rng.random::<f32>())
}

/// Paints a "dead leaves" patchwork of `count` shapes sized `lo..hi` texels.
fn dead_leaves(
    c: &mut Canvas,
    rng: &mut StdRng,
    count: usize,
    lo: f32,
    hi: f32,
    gray: (f32, f32),
    alpha: (f32, f32),
) {
    let n = c.size() as f32;
    for _ in 0..count {
        let centre = (rng.random_range(0.0..n), rng.random_range(0.0..n));
        let s = log_uniform(rng, lo, hi);
        let value = rng.random_range(gray.0..gray.1);
        let a = rng.random_range(alpha.0..alpha.1);
        match rng.random_range(0..5) {
            0 | 1 => {
                let aspect = rng.random_range(0.3..1.0);
                c.rect(
                    centre,
                    (s * 0.5, s * 0.5 * aspect),
                    rng.random_range(0.0..3.2),
                    value,
                    a,
                )
            }
            2 => c.disc(centre, s * 0.5, value, a),
            3 => c.ring(centre, s * 0.5, (s * 0.1).max(1.0), value, a),
            _ => {
                let ang: f32 = rng.random_range(0.0..6.3);
                let half = (ang.cos() * s * 0.5, ang.sin() * s * 0.5);
                c.line(
                    (centre.0 - half.0, centre.1 - half.1),
                    (centre.0 + half.0, centre.1 + half.1),
                    (s * 0.08).max(1.0),
                    value,
                    a,
                )
            }
        }
    }
}

fn detail_texture(size: usize, seed: u64) -> MipTexture {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut c = Canvas::new(size, 128.0);
    c.add_fbm(4, 10, 22.0, 0.6, seed ^ 1);
    let k = size as f32 / 1024.0;
    dead_leaves(
        &mut c,
        &mut rng,
        (3500.0 * k * k) as usize + 50,
        2.0 * k,
        40.0 * k,
        (30.0, 230.0),
        (0.5, 1.0),
    );
    // Cracks.
    for _ in 0..(40.0 * k * k) as usize + 4 {
        let mut p = (
            rng.random_range(0.0..size as f32),
            rng.random_range(0.0..size as f32),
        );
        let mut ang: f32 = rng.random_range(0.0..6.3);
        for _ in 0..rng.random_range(3..12) {
            ang += rng.random_range(-0.8..0.8);
            let len = rng.random_range(6.0..30.0) * k;
            let q = (p.0 + ang.cos() * len, p.1 + ang.sin() * len);
            c.line(p, q, 1.2 * k.max(0.5), 35.0, 0.8);
            p = q;
        }
    }
    c.into_mip()
}

fn make_textures(
    seed: u64,
    p: &WorldParams,
    roads: &[Road],
    boxes: &[SceneBox],
    sun: &Vector3<f64>,
) -> Textures {
    let ground_inv_texel = (p.ground_texture_size as f64 / p.ground_extent_m) as f32;
    let timed = |name: &str, f: &dyn Fn() -> MipTexture| {
        let t0 = std::time::Instant::now();
        let t = f();
        tracing::debug!(
            texture = name,
            seconds = t0.elapsed().as_secs_f64(),
            "texture generated"
        );
        t
    };
    let ground = timed("ground", &|| {
        ground_texture(seed, p, roads, boxes, sun, ground_inv_texel)
    });
    let far = timed("far", &|| far_texture(seed, p));
    let facade = timed("facade", &|| facade_texture(seed, p));
    let roof = timed("roof", &|| roof_texture(seed, p));
    let detail_a = timed("detail_a", &|| {
        detail_texture(p.detail_texture_size, seed ^ 0xA11CE)
    });
    let detail_b = timed("detail_b", &|| {
        detail_texture(p.detail_texture_size, seed ^ 0xB0B)
    });
    let rot = 35.0f32.to_radians();
    let close_rot = 101.0f32.to_radians();
    Textures {
        ground,
        ground_inv_texel,
        ground_half_extent: (p.ground_extent_m * 0.5) as f32,
        far,
        far_inv_texel: (p.far_texture_size as f64 / p.far_extent_m) as f32,
        facade,
        facade_inv_texel: (p.facade_texture_size as f64 / p.facade_extent_m) as f32,
        roof,
        roof_inv_texel: (p.roof_texture_size as f64 / p.roof_extent_m) as f32,
        detail_a,
        detail_a_inv_texel: (p.detail_texture_size as f64 / p.detail_extent_m) as f32,
        detail_a_log2_inv_texel: (p.detail_texture_size as f64 / p.detail_extent_m).log2() as f32,
        detail_b,
        detail_b_inv_texel: (p.detail_texture_size as f64 / (p.detail_extent_m * PHI)) as f32,
        detail_b_log2_inv_texel: (p.detail_texture_size as f64 / (p.detail_extent_m * PHI)).log2()
            as f32,
        detail_b_rot: (rot.cos(), rot.sin()),
        detail_close_rot: (close_rot.cos(), close_rot.sin()),
        foliage: (p.kind == WorldKind::Trees).then(|| foliage_texture(seed)),
        foliage_inv_texel: FOLIAGE_TEXELS as f32 / FOLIAGE_TILE_M,
    }
}

fn ground_texture(
    seed: u64,
    p: &WorldParams,
    roads: &[Road],
    boxes: &[SceneBox],
    sun: &Vector3<f64>,
    s: f32,
) -> MipTexture {
    if !matches!(p.kind, WorldKind::Town | WorldKind::Traffic) {
        return kind_ground_texture(seed, p, boxes, sun, s);
    }
    let mut rng = StdRng::seed_from_u64(seed ^ 0x6E0D);
    let n = p.ground_texture_size;
    let h = (p.ground_extent_m * 0.5) as f32;
    let to_tex = |x: f64, y: f64| (((x as f32) + h) * s, ((y as f32) + h) * s);
    let mut c = Canvas::new(n, 112.0);
    c.add_fbm(8, 12, 38.0, 0.55, seed ^ 11);
    let area_scale = (p.ground_extent_m * p.ground_extent_m / 65536.0) as f32;
    // Lawns, paving, dirt: a patchwork from 0.25 m to 10 m.
    dead_leaves(
        &mut c,
        &mut rng,
        (14000.0 * area_scale) as usize,
        0.25 * s,
        10.0 * s,
        (45.0, 215.0),
        (0.35, 1.0),
    );
    // Small high-contrast litter: stones, leaves, paint spots.
    dead_leaves(
        &mut c,
        &mut rng,
        (30000.0 * area_scale) as usize,
        0.06 * s,
        0.5 * s,
        (20.0, 240.0),
        (0.6, 1.0),
    );
    // Parking lots with stall lines.
    for _ in 0..(12.0 * area_scale) as usize {
        let cx = rng.random_range(-p.scene_radius_m..p.scene_radius_m);
        let cy = rng.random_range(-p.scene_radius_m..p.scene_radius_m);
        let (w, d) = (
            rng.random_range(15.0..35.0f32),
            rng.random_range(12.0..24.0f32),
        );
        c.rect(
            to_tex(cx, cy),
            (w * 0.5 * s, d * 0.5 * s),
            0.0,
            rng.random_range(60.0..90.0),
            1.0,
        );
        let stall = rng.random_range(2.4..2.8f32);
        let mut x = -w * 0.5 + 1.0;
        while x < w * 0.5 - 1.0 {
            for side in [-1.0f32, 1.0] {
                let a = to_tex(cx + x as f64, cy + (side * d * 0.5 * 0.9) as f64);
                let b = to_tex(cx + x as f64, cy + (side * d * 0.5 * 0.25) as f64);
                c.line(a, b, 0.12 * s, 225.0, 0.9);
            }
            x += stall;
        }
    }
    // Roads: sidewalks with joints, asphalt, edge lines, dashed centre line.
    let lim = p.ground_extent_m * 0.5;
    for r in roads {
        let seg = |along: f64, across: f64| {
            if r.along_x {
                to_tex(along, across)
            } else {
                to_tex(across, along)
            }
        };
        let half_w = r.width * 0.5;
        let walk = 2.5;
        let (walk_a, walk_b) = (
            seg(-lim, r.centre - half_w - walk * 0.5),
            seg(lim, r.centre - half_w - walk * 0.5),
        );
        c.line(walk_a, walk_b, (walk * s as f64) as f32, 165.0, 1.0);
        let (walk_a, walk_b) = (
            seg(-lim, r.centre + half_w + walk * 0.5),
            seg(lim, r.centre + half_w + walk * 0.5),
        );
        c.line(walk_a, walk_b, (walk * s as f64) as f32, 165.0, 1.0);
        let mut t = -lim + rng.random_range(0.0..1.5);
        while t < lim {
            for side in [-1.0, 1.0] {
                let a = seg(t, r.centre + side * half_w);
                let b = seg(t, r.centre + side * (half_w + walk));
                c.line(a, b, 0.05 * s, 95.0, 0.8);
            }
            t += rng.random_range(1.2..2.2);
        }
        c.line(
            seg(-lim, r.centre),
            seg(lim, r.centre),
            (r.width * s as f64) as f32,
            72.0,
            1.0,
        );
        for side in [-1.0, 1.0] {
            let off = r.centre + side * (half_w - 0.4);
            c.line(seg(-lim, off), seg(lim, off), 0.15 * s, 215.0, 0.95);
        }
        let mut t = -lim;
        let dash = rng.random_range(2.5..4.0);
        let gap = rng.random_range(4.0..7.0);
        while t < lim {
            c.line(
                seg(t, r.centre),
                seg(t + dash, r.centre),
                0.15 * s,
                220.0,
                0.95,
            );
            t += dash + gap;
        }
    }
    // Crosswalks at some intersections.
    for a in roads.iter().filter(|r| r.along_x) {
        for b in roads.iter().filter(|r| !r.along_x) {
            if !rng.random_bool(0.6) {
                continue;
            }
            // Intersection at x = b.centre, y = a.centre; stripes across road a.
            let x0 = b.centre + (b.width * 0.5 + 1.5);
            let mut y = a.centre - a.width * 0.5 + 0.5;
            while y < a.centre + a.width * 0.5 - 0.5 {
                c.line(to_tex(x0, y), to_tex(x0 + 3.0, y), 0.5 * s, 230.0, 0.95);
                y += 1.0;
            }
        }
    }
    // Grime and light variation, then shadows of the boxes.
    c.modulate_fbm(16, 9, 0.22, seed ^ 0x9A1);
    bake_shadows(&mut c, p, boxes, sun, s, h);
    c.into_mip()
}

/// Darkens ground texels from which the ray towards the sun hits a box.
fn bake_shadows(
    c: &mut Canvas,
    p: &WorldParams,
    boxes: &[SceneBox],
    sun: &Vector3<f64>,
    s: f32,
    h: f32,
) {
    let n = c.size();
    let k = -1.0 / sun.z; // horizontal displacement per metre of height
    let (dx, dy) = (sun.x * k, sun.y * k);
    let factor = p.shadow_factor;
    let data = c.data_mut();
    for b in boxes {
        let ht = b.height();
        let (sx, sy) = (dx * ht, dy * ht);
        // The shadow is the footprint swept away from the sun.
        let x_lo = b.min.x.min(b.min.x - sx);
        let x_hi = b.max.x.max(b.max.x - sx);
        let y_lo = b.min.y.min(b.min.y - sy);
        let y_hi = b.max.y.max(b.max.y - sy);
        let tx0 = (((x_lo as f32 + h) * s).floor().max(0.0)) as usize;
        let tx1 = ((((x_hi as f32 + h) * s).ceil()).max(0.0) as usize).min(n);
        let ty0 = (((y_lo as f32 + h) * s).floor().max(0.0)) as usize;
        let ty1 = ((((y_hi as f32 + h) * s).ceil()).max(0.0) as usize).min(n);
        for ty in ty0..ty1 {
            let y = (ty as f64 + 0.5) / s as f64 - h as f64;
            for tx in tx0..tx1 {
                let x = (tx as f64 + 0.5) / s as f64 - h as f64;
                // Ray (x, y) + λ (dx, dy) for λ ∈ [0, ht]: does it cross the footprint?
                // A box above the ground (a tree's crown) shades from its underside up.
                let mut lo = if b.max.z < 0.0 { -b.max.z } else { 0.0 };
                let mut hi = ht;
                for (o, d, mn, mx) in [(x, dx, b.min.x, b.max.x), (y, dy, b.min.y, b.max.y)] {
                    if d.abs() < 1e-12 {
                        if o < mn || o > mx {
                            hi = -1.0;
                        }
                    } else {
                        let (mut a, mut bb) = ((mn - o) / d, (mx - o) / d);
                        if a > bb {
                            std::mem::swap(&mut a, &mut bb);
                        }
                        lo = lo.max(a);
                        hi = hi.min(bb);
                    }
                }
                if lo <= hi {
                    // Texel coordinates are (u = x, v = y): row = v.
                    data[ty * n + tx] *= factor;
                }
            }
        }
    }
}

fn far_texture(seed: u64, p: &WorldParams) -> MipTexture {
    let mut rng = StdRng::seed_from_u64(seed ^ 0xFA7);
    let n = p.far_texture_size;
    let s = (n as f64 / p.far_extent_m) as f32;
    let mut c = Canvas::new(n, 105.0);
    c.add_fbm(8, 8, 30.0, 0.55, seed ^ 21);
    let k = (n * n) as f32 / (1024.0 * 1024.0);
    // Fields and lots from 20 m to 400 m, with roads between them.
    dead_leaves(
        &mut c,
        &mut rng,
        (2500.0 * k) as usize + 20,
        20.0 * s,
        400.0 * s,
        (60.0, 185.0),
        (0.7, 1.0),
    );
    for _ in 0..(60.0 * k) as usize + 4 {
        let along_x = rng.random_bool(0.5);
        let off = rng.random_range(0.0..n as f32);
        let (a, b) = if along_x {
            ((0.0, off), (n as f32, off))
        } else {
            ((off, 0.0), (off, n as f32))
        };
        c.line(a, b, (8.0 * s).max(1.0), 75.0, 0.9);
    }
    c.modulate_fbm(8, 6, 0.15, seed ^ 22);
    c.into_mip()
}

fn facade_texture(seed: u64, p: &WorldParams) -> MipTexture {
    let mut rng = StdRng::seed_from_u64(seed ^ 0xFACADE);
    let n = p.facade_texture_size;
    let s = (n as f64 / p.facade_extent_m) as f32;
    let mut c = Canvas::new(n, 150.0);
    c.add_fbm(16, 10, 18.0, 0.6, seed ^ 31);
    let blocks = (p.facade_extent_m / 32.0).round().max(1.0) as usize;
    let block_m = p.facade_extent_m as f32 / blocks as f32;
    for by in 0..blocks {
        for bx in 0..blocks {
            let (x0, y0) = (bx as f32 * block_m, by as f32 * block_m);
            let wall = rng.random_range(95.0..205.0);
            c.rect(
                ((x0 + block_m * 0.5) * s, (y0 + block_m * 0.5) * s),
                (block_m * 0.5 * s, block_m * 0.5 * s),
                0.0,
                wall,
                1.0,
            );
            let floor_h = rng.random_range(2.9..4.2f32);
            let win_w = rng.random_range(0.7..2.2f32);
            let win_h = rng.random_range(0.9..2.0f32).min(floor_h - 0.6);
            let pitch = win_w + rng.random_range(0.5..2.5f32);
            let glass_dark = rng.random_bool(0.6);
            let frame = (wall + rng.random_range(-60.0..60.0f32)).clamp(20.0, 240.0);
            let sill = rng.random_range(0.6..1.0f32);
            // Ground floor: a door or a shop front, then floors of windows.
            let mut v = 0.0f32;
            let mut floor = 0;
            while v + floor_h <= block_m {
                // Floor band line.
                c.line(
                    (x0 * s, (y0 + v) * s),
                    ((x0 + block_m) * s, (y0 + v) * s),
                    0.2 * s,
                    frame,
                    0.9,
                );
                let mut u = rng.random_range(0.3..pitch);
                while u + win_w < block_m {
                    let skip = floor == 0 && rng.random_bool(0.3);
                    if !skip {
                        let cu = x0 + u + win_w * 0.5;
                        let cv = y0 + v + sill + win_h * 0.5;
                        let glass = if glass_dark {
                            rng.random_range(15.0..70.0)
                        } else {
                            rng.random_range(110.0..200.0)
                        };
                        c.rect(
                            (cu * s, cv * s),
                            ((win_w * 0.5 + 0.08) * s, (win_h * 0.5 + 0.08) * s),
                            0.0,
                            frame,
                            1.0,
                        );
                        c.rect(
                            (cu * s, cv * s),
                            (win_w * 0.5 * s, win_h * 0.5 * s),
                            0.0,
                            glass,
                            1.0,
                        );
                        // Blinds pulled down part way (from the top, v grows upwards).
                        if rng.random_bool(0.45) {
                            let frac = rng.random_range(0.15..0.9f32);
                            let bh = win_h * frac;
                            let top = y0 + v + sill + win_h;
                            c.rect(
                                (cu * s, (top - bh * 0.5) * s),
                                (win_w * 0.5 * s, bh * 0.5 * s),
                                0.0,
                                rng.random_range(150.0..235.0),
                                1.0,
                            );
                        }
                        // Mullion.
                        if win_w > 1.2 {
                            c.line(
                                (cu * s, (cv - win_h * 0.5) * s),
                                (cu * s, (cv + win_h * 0.5) * s),
                                0.08 * s,
                                frame,
                                1.0,
                            );
                        }
                    }
                    u += pitch;
                }
                v += floor_h;
                floor += 1;
            }
        }
    }
    // Posters, stains, signs.
    dead_leaves(
        &mut c,
        &mut rng,
        (600.0 * (p.facade_extent_m / 128.0).powi(2)) as usize,
        0.3 * s,
        3.0 * s,
        (20.0, 235.0),
        (0.3, 0.9),
    );
    c.modulate_fbm(8, 8, 0.2, seed ^ 32);
    c.into_mip()
}

fn roof_texture(seed: u64, p: &WorldParams) -> MipTexture {
    let mut rng = StdRng::seed_from_u64(seed ^ 0x400F);
    let n = p.roof_texture_size;
    let s = (n as f64 / p.roof_extent_m) as f32;
    let mut c = Canvas::new(n, 125.0);
    c.add_fbm(8, 10, 30.0, 0.6, seed ^ 41);
    let k = (p.roof_extent_m / 51.2).powi(2) as f32;
    // Roofing membrane seams.
    let mut x = 0.0f32;
    while x < p.roof_extent_m as f32 {
        c.line((x * s, 0.0), (x * s, n as f32), 0.06 * s, 95.0, 0.7);
        x += rng.random_range(1.0..2.5);
    }
    // AC units, skylights, vents, pipes.
    dead_leaves(
        &mut c,
        &mut rng,
        (500.0 * k) as usize + 10,
        0.4 * s,
        3.5 * s,
        (50.0, 235.0),
        (0.85, 1.0),
    );
    for _ in 0..(80.0 * k) as usize + 4 {
        let a = (
            rng.random_range(0.0..n as f32),
            rng.random_range(0.0..n as f32),
        );
        let len = rng.random_range(2.0..10.0) * s;
        let (b, w) = if rng.random_bool(0.5) {
            ((a.0 + len, a.1), 0.15 * s)
        } else {
            ((a.0, a.1 + len), 0.15 * s)
        };
        c.line(a, b, w, rng.random_range(40.0..220.0), 1.0);
    }
    c.modulate_fbm(8, 8, 0.2, seed ^ 42);
    c.into_mip()
}

/// Metres across one tile of the foliage texture (it repeats: foliage is
/// repetitive).
const FOLIAGE_TILE_M: f32 = 2.0;
/// Texels across the foliage tile.
const FOLIAGE_TEXELS: usize = 128;

impl WorldKind {
    /// The kind's own texture settings (the town keeps the parameters as
    /// given): smooth surfaces carry less close-up detail.
    fn adjust(self, p: &mut WorldParams) {
        let detail = match self {
            WorldKind::Town | WorldKind::Traffic | WorldKind::Aliasing => return,
            WorldKind::Grass => 0.3,
            WorldKind::Carpark => 0.35,
            WorldKind::Trees => 0.5,
            WorldKind::Water => 0.5,
        };
        p.detail_gain_a *= detail;
        p.detail_gain_b *= detail;
        p.detail_gain_close *= detail;
    }
}

/// Layout of `params.kind`: roads, boxes, movers, water.
fn layout_kind(
    rng: &mut StdRng,
    seed: u64,
    p: &WorldParams,
) -> (Vec<Road>, Vec<SceneBox>, Vec<Mover>, Vec<WaterBody>) {
    match p.kind {
        WorldKind::Town => {
            let roads = layout_roads(rng, p);
            let boxes = layout_boxes(rng, p, &roads);
            (roads, boxes, Vec::new(), Vec::new())
        }
        WorldKind::Traffic => {
            let roads = layout_roads(rng, p);
            let boxes = layout_boxes(rng, p, &roads);
            let movers = traffic_movers(seed, p, &roads, &boxes);
            (roads, boxes, movers, Vec::new())
        }
        WorldKind::Grass => (Vec::new(), layout_grass(rng, p), Vec::new(), Vec::new()),
        WorldKind::Carpark => {
            let mut boxes = Vec::new();
            carpark_cars(rng, p, &mut boxes, p.scene_radius_m, 0.7);
            // Identical pay stations along the edge.
            for k in 0..4 {
                let y = -60.0 + 40.0 * k as f64;
                boxes.push(identical_box(
                    BoxKind::Kiosk,
                    (p.scene_radius_m + 8.0, y),
                    (3.0, 2.0, 2.6),
                    1.5,
                ));
            }
            (Vec::new(), boxes, Vec::new(), Vec::new())
        }
        WorldKind::Trees => (Vec::new(), layout_trees(rng, p), Vec::new(), Vec::new()),
        WorldKind::Water => {
            let water = vec![
                WaterBody {
                    min: [16.0, -160.0],
                    max: [160.0, 160.0],
                },
                WaterBody {
                    min: [-160.0, -160.0],
                    max: [-16.0, 160.0],
                },
            ];
            (Vec::new(), layout_shore(rng, p), Vec::new(), water)
        }
        WorldKind::Aliasing => {
            let mut boxes = Vec::new();
            // A grid of identical buildings, the centre left for the car park.
            let pitch = 34.0;
            for i in -3i32..=3 {
                for j in -3i32..=3 {
                    if i.abs() <= 1 && j.abs() <= 1 {
                        continue;
                    }
                    let c = (i as f64 * pitch, j as f64 * pitch);
                    if c.0.hypot(c.1) > p.scene_radius_m + 10.0 {
                        continue;
                    }
                    boxes.push(identical_box(BoxKind::Building, c, (16.0, 12.0, 12.0), 1.0));
                }
            }
            carpark_cars(rng, p, &mut boxes, 1.45 * pitch, 0.75);
            (Vec::new(), boxes, Vec::new(), Vec::new())
        }
    }
}

/// A box of `size` (length along x, width along y, height) centred at
/// `centre` whose look is the same wherever it stands.
fn identical_box(kind: BoxKind, centre: (f64, f64), size: (f64, f64, f64), scale: f32) -> SceneBox {
    SceneBox {
        min: Vector3::new(centre.0 - size.0 * 0.5, centre.1 - size.1 * 0.5, -size.2),
        max: Vector3::new(centre.0 + size.0 * 0.5, centre.1 + size.1 * 0.5, 0.0),
        kind,
        facade_offset: [17.0, 32.0],
        roof_offset: [11.0, 23.0],
        texture_scale: scale,
        albedo: 1.0,
        local_texture: true,
    }
}

/// The car park's geometry: rows of stalls along y, with aisles.
struct StallGrid {
    /// Stall width (along y), m.
    width: f64,
    /// Stall depth (along x), m.
    depth: f64,
    /// Distance between the centres of two double rows, m.
    pitch: f64,
}

const STALLS: StallGrid = StallGrid {
    width: 2.5,
    depth: 5.0,
    pitch: 16.5,
};

/// Centres of the stalls within `radius` of home (outside the take-off
/// area), and whether each faces +x.
fn stall_centres(radius: f64) -> Vec<(f64, f64, bool)> {
    let g = &STALLS;
    let mut out = Vec::new();
    let rows = (radius / g.pitch).ceil() as i32;
    for r in -rows..=rows {
        let x0 = r as f64 * g.pitch;
        for side in [-1.0, 1.0] {
            let x = x0 + side * g.depth * 0.5;
            let n = (radius / g.width).ceil() as i32;
            for k in -n..n {
                let y = (k as f64 + 0.5) * g.width;
                if x.hypot(y) <= radius && x.hypot(y) > 12.0 {
                    out.push((x, y, side > 0.0));
                }
            }
        }
    }
    out
}

/// Identical cars in a share of the stalls within `radius`.
fn carpark_cars(
    rng: &mut StdRng,
    p: &WorldParams,
    boxes: &mut Vec<SceneBox>,
    radius: f64,
    share: f64,
) {
    let _ = p;
    for (x, y, _) in stall_centres(radius) {
        if rng.random_bool(share) {
            boxes.push(identical_box(BoxKind::Car, (x, y), (4.5, 1.8, 1.5), 2.5));
        }
    }
}

/// Open grass: a few sheds and hay bales far apart.
fn layout_grass(rng: &mut StdRng, p: &WorldParams) -> Vec<SceneBox> {
    let mut boxes = Vec::new();
    for _ in 0..6 {
        let r = p.scene_radius_m * (0.4 + 0.6 * rng.random::<f64>());
        let a = rng.random_range(0.0..std::f64::consts::TAU);
        let (l, w, h) = (
            rng.random_range(1.5..4.0),
            rng.random_range(1.5..3.0),
            rng.random_range(1.2..2.8),
        );
        let (cx, cy) = (r * a.cos(), r * a.sin());
        boxes.push(SceneBox {
            min: Vector3::new(cx - l * 0.5, cy - w * 0.5, -h),
            max: Vector3::new(cx + l * 0.5, cy + w * 0.5, 0.0),
            kind: BoxKind::Kiosk,
            facade_offset: [rng.random_range(0.0..128.0), rng.random_range(0.0..128.0)],
            roof_offset: [rng.random_range(0.0..51.2), rng.random_range(0.0..51.2)],
            texture_scale: 1.5,
            albedo: rng.random_range(0.7..1.1),
            local_texture: false,
        });
    }
    boxes
}

/// An orchard-like wood: rows of trees 7 m apart (jittered), each a trunk
/// and a crown of the same size.
fn layout_trees(rng: &mut StdRng, p: &WorldParams) -> Vec<SceneBox> {
    let mut boxes = Vec::new();
    let pitch = 7.0;
    let n = (p.scene_radius_m * 1.2 / pitch).ceil() as i32;
    for i in -n..=n {
        for j in -n..=n {
            let (cx, cy) = (
                i as f64 * pitch + rng.random_range(-1.0..1.0),
                j as f64 * pitch + rng.random_range(-1.0..1.0),
            );
            let r = cx.hypot(cy);
            if r < p.clear_radius_m || r > p.scene_radius_m * 1.2 {
                continue;
            }
            let crown = 4.6;
            let top = 8.0;
            let bottom = 3.2;
            boxes.push(SceneBox {
                min: Vector3::new(cx - crown * 0.5, cy - crown * 0.5, -top),
                max: Vector3::new(cx + crown * 0.5, cy + crown * 0.5, -bottom),
                kind: BoxKind::Tree,
                facade_offset: [0.0, 0.0],
                roof_offset: [0.0, 0.0],
                texture_scale: 1.0,
                albedo: 1.0,
                local_texture: true,
            });
            boxes.push(SceneBox {
                min: Vector3::new(cx - 0.2, cy - 0.2, -bottom),
                max: Vector3::new(cx + 0.2, cy + 0.2, 0.0),
                kind: BoxKind::Kiosk,
                facade_offset: [40.0, 5.0],
                roof_offset: [0.0, 0.0],
                texture_scale: 4.0,
                albedo: 0.45,
                local_texture: true,
            });
        }
    }
    boxes
}

/// Buildings along the strip of land between the lakes.
fn layout_shore(rng: &mut StdRng, p: &WorldParams) -> Vec<SceneBox> {
    let mut boxes = Vec::new();
    let mut y = -p.scene_radius_m;
    while y < p.scene_radius_m {
        let w = rng.random_range(8.0..16.0);
        if (y + w * 0.5).abs() > p.clear_radius_m + w * 0.5 {
            let d = rng.random_range(6.0..10.0);
            let h = rng.random_range(5.0..18.0);
            let cx = rng.random_range(-1.0..1.0);
            boxes.push(SceneBox {
                min: Vector3::new(cx - d * 0.5, y, -h),
                max: Vector3::new(cx + d * 0.5, y + w, 0.0),
                kind: BoxKind::Building,
                facade_offset: [
                    rng.random_range(0.0..128.0),
                    32.0 * rng.random_range(0..4) as f32,
                ],
                roof_offset: [rng.random_range(0.0..51.2), rng.random_range(0.0..51.2)],
                texture_scale: 1.0,
                albedo: rng.random_range(0.8..1.15),
                local_texture: false,
            });
        }
        y += w + rng.random_range(3.0..8.0);
    }
    boxes
}

/// The town's cars on roads drive: each along its road at 5-14 m/s (either
/// way), wrapping around the stretch of road inside the ground texture.
/// Seeded apart from the layout, so the town's layout is unchanged.
fn traffic_movers(seed: u64, p: &WorldParams, roads: &[Road], boxes: &[SceneBox]) -> Vec<Mover> {
    let mut rng = StdRng::seed_from_u64(seed ^ 0x7AFF1C);
    let lim = p.ground_extent_m * 0.5 - 4.0;
    boxes
        .iter()
        .enumerate()
        .filter(|(_, b)| b.kind == BoxKind::Car)
        .filter_map(|(index, b)| {
            let c = (b.min + b.max) * 0.5;
            let road = roads.iter().find(|r| {
                let across = if r.along_x { c.y } else { c.x };
                (across - r.centre).abs() < r.width * 0.5
            })?;
            // Drive on the right: the lane's side sets the direction.
            let across = if road.along_x { c.y } else { c.x };
            let sign = if across > road.centre { 1.0 } else { -1.0 };
            Some(Mover {
                index,
                along_x: road.along_x,
                speed_m_s: sign * rng.random_range(5.0..14.0),
                lo: -lim,
                hi: lim,
            })
        })
        .collect()
}

/// The ground of the kinds other than the town.
fn kind_ground_texture(
    seed: u64,
    p: &WorldParams,
    boxes: &[SceneBox],
    sun: &Vector3<f64>,
    s: f32,
) -> MipTexture {
    let mut rng = StdRng::seed_from_u64(seed ^ 0x6E0D ^ (p.kind as u64) << 32);
    let n = p.ground_texture_size;
    let h = (p.ground_extent_m * 0.5) as f32;
    let to_tex = |x: f64, y: f64| (((x as f32) + h) * s, ((y as f32) + h) * s);
    let area = (p.ground_extent_m * p.ground_extent_m / 65536.0) as f32;
    let mut c = match p.kind {
        WorldKind::Carpark | WorldKind::Aliasing => {
            let mut c = Canvas::new(n, 74.0);
            c.add_fbm(8, 10, 10.0, 0.5, seed ^ 51);
            // Oil stains and patches: faint.
            dead_leaves(
                &mut c,
                &mut rng,
                (3000.0 * area) as usize,
                0.2 * s,
                1.5 * s,
                (55.0, 90.0),
                (0.3, 0.6),
            );
            let radius = if p.kind == WorldKind::Carpark {
                p.scene_radius_m
            } else {
                1.45 * 34.0
            };
            paint_stalls(&mut c, radius, &to_tex, s);
            if p.kind == WorldKind::Aliasing {
                // Pavements around the identical buildings.
                for b in boxes.iter().filter(|b| b.kind == BoxKind::Building) {
                    let cx = (b.min.x + b.max.x) * 0.5;
                    let cy = (b.min.y + b.max.y) * 0.5;
                    let half = (
                        ((b.max.x - b.min.x) * 0.5 + 3.0) as f32 * s,
                        ((b.max.y - b.min.y) * 0.5 + 3.0) as f32 * s,
                    );
                    c.rect(to_tex(cx, cy), half, 0.0, 160.0, 1.0);
                }
            }
            c
        }
        WorldKind::Trees => {
            // A repeating forest floor: one 2 m tile of leaf litter copied everywhere.
            let tile = forest_floor_tile(seed, (2.0 * s) as usize);
            let mut c = Canvas::new(n, 0.0);
            let t = tile.size();
            let data = c.data_mut();
            for y in 0..n {
                for x in 0..n {
                    data[y * n + x] = tile.data()[(y % t) * t + x % t];
                }
            }
            c.modulate_fbm(8, 4, 0.15, seed ^ 61);
            c
        }
        WorldKind::Water => {
            // The land between the lakes: grass and a paved promenade.
            let mut c = grass_canvas(n, seed, &mut rng, s, area);
            c.rect(to_tex(0.0, 0.0), (3.0 * s, h * s), 0.0, 150.0, 1.0);
            c
        }
        // Grass (the town kinds never reach here).
        _ => {
            let mut c = grass_canvas(n, seed, &mut rng, s, area);
            // A winding dirt path.
            let mut pt = (-p.scene_radius_m, -20.0);
            let mut heading: f64 = 0.2;
            while pt.0 < p.scene_radius_m {
                heading += rng.random_range(-0.25..0.25);
                heading = heading.clamp(-0.8, 0.8);
                let next = (pt.0 + 6.0 * heading.cos(), pt.1 + 6.0 * heading.sin());
                c.line(
                    to_tex(pt.0, pt.1),
                    to_tex(next.0, next.1),
                    1.2 * s,
                    128.0,
                    0.8,
                );
                pt = next;
            }
            c
        }
    };
    bake_shadows(&mut c, p, boxes, sun, s, h);
    c.into_mip()
}

/// Mown grass: low-contrast noise, mowing stripes 3 m wide, faint clover.
fn grass_canvas(n: usize, seed: u64, rng: &mut StdRng, s: f32, area: f32) -> Canvas {
    let mut c = Canvas::new(n, 100.0);
    c.add_fbm(8, 10, 9.0, 0.5, seed ^ 71);
    let stripe = (3.0 * s).max(1.0);
    let nf = n as f32;
    let mut x = 0.0;
    let mut light = true;
    while x < nf {
        c.rect(
            (x + stripe * 0.5, nf * 0.5),
            (stripe * 0.5, nf * 0.5),
            0.0,
            if light { 106.0 } else { 96.0 },
            0.6,
        );
        light = !light;
        x += stripe;
    }
    dead_leaves(
        &mut c,
        rng,
        (4000.0 * area) as usize,
        0.05 * s,
        0.3 * s,
        (92.0, 118.0),
        (0.3, 0.6),
    );
    c.modulate_fbm(16, 6, 0.05, seed ^ 72);
    c
}

/// Stall lines of the car park within `radius` of home.
fn paint_stalls(c: &mut Canvas, radius: f64, to_tex: &dyn Fn(f64, f64) -> (f32, f32), s: f32) {
    let g = &STALLS;
    let line = 0.12 * s;
    for (x, y, _) in stall_centres(radius) {
        // The two side lines of the stall and its end line.
        let (x0, x1) = (x - g.depth * 0.5, x + g.depth * 0.5);
        for yy in [y - g.width * 0.5, y + g.width * 0.5] {
            c.line(to_tex(x0, yy), to_tex(x1, yy), line, 225.0, 0.95);
        }
    }
    // The aisle centre lines (dashed).
    let rows = (radius / g.pitch).ceil() as i32;
    for r in -rows..=rows {
        let x = (r as f64 + 0.5) * g.pitch;
        let mut y = -radius;
        while y < radius {
            c.line(to_tex(x, y), to_tex(x, y + 2.0), line, 210.0, 0.9);
            y += 5.0;
        }
    }
}

/// A tile of leaf litter `texels` across.
fn forest_floor_tile(seed: u64, texels: usize) -> Canvas {
    let mut rng = StdRng::seed_from_u64(seed ^ 0xF10);
    let n = texels.max(8).next_power_of_two();
    let mut c = Canvas::new(n, 70.0);
    c.add_fbm(4, 6, 12.0, 0.6, seed ^ 0xF11);
    dead_leaves(
        &mut c,
        &mut rng,
        n * n / 24,
        1.0,
        n as f32 / 6.0,
        (35.0, 140.0),
        (0.6, 1.0),
    );
    c
}

/// The repeating foliage of the trees: leaves 4-20 cm on a 2 m tile.
fn foliage_texture(seed: u64) -> MipTexture {
    let mut rng = StdRng::seed_from_u64(seed ^ 0xF0_11A6E);
    let n = FOLIAGE_TEXELS;
    let s = n as f32 / FOLIAGE_TILE_M;
    let mut c = Canvas::new(n, 60.0);
    c.add_fbm(4, 5, 15.0, 0.6, seed ^ 0xF12);
    dead_leaves(
        &mut c,
        &mut rng,
        n * n / 6,
        0.04 * s,
        0.2 * s,
        (30.0, 150.0),
        (0.7, 1.0),
    );
    c.into_mip()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn generation_is_deterministic_and_respects_the_layout_rules() {
        let p = WorldParams::tiny();
        let a = World::generate_with(5, &p).unwrap();
        let b = World::generate_with(5, &p).unwrap();
        let c = World::generate_with(6, &p).unwrap();
        assert_eq!(a.boxes, b.boxes);
        assert_ne!(a.boxes, c.boxes);
        assert_eq!(
            a.textures.ground.texel(100, 200),
            b.textures.ground.texel(100, 200)
        );
        let buildings: Vec<_> = a
            .boxes
            .iter()
            .filter(|b| b.kind == BoxKind::Building)
            .collect();
        assert!(buildings.len() >= 30, "{} buildings", buildings.len());
        assert!(a.boxes.len() - buildings.len() >= 40);
        // Several sizes.
        let heights: Vec<f64> = buildings.iter().map(|b| b.height()).collect();
        assert!(heights.iter().cloned().fold(0.0, f64::max) > 15.0);
        assert!(heights.iter().cloned().fold(100.0, f64::min) < 8.0);
        for b in &a.boxes {
            assert_eq!(b.max.z, 0.0);
            assert!(b.min.z < 0.0);
            let c = (b.min + b.max) * 0.5;
            assert!(c.x.hypot(c.y) <= p.scene_radius_m + 1.0);
        }
        // Take-off area is clear.
        assert_eq!(a.max_height_near(0.0, 0.0, 5.0), 0.0);
        // Boxes do not overlap.
        for (i, x) in a.boxes.iter().enumerate() {
            for y in &a.boxes[i + 1..] {
                let sep = x.max.x <= y.min.x
                    || y.max.x <= x.min.x
                    || x.max.y <= y.min.y
                    || y.max.y <= x.min.y;
                assert!(sep, "{x:?} overlaps {y:?}");
            }
        }
    }

    #[test]
    fn ray_cast_hits_ground_and_boxes() {
        let w = World::generate_with(1, &WorldParams::tiny()).unwrap();
        let o = Point3::new(0.0, 0.0, -20.0);
        let hit = w.ray_cast(&o, &Vector3::new(0.0, 0.0, 1.0), 1e4).unwrap();
        assert_eq!(hit.surface, Surface::Ground);
        assert!((hit.t - 20.0).abs() < 1e-9);
        // Looking up: nothing.
        assert!(w.ray_cast(&o, &Vector3::new(0.1, 0.0, -1.0), 1e4).is_none());
        // Straight down onto a building roof.
        let b = w
            .boxes
            .iter()
            .find(|b| b.kind == BoxKind::Building)
            .unwrap();
        let c = (b.min + b.max) * 0.5;
        let hit = w
            .ray_cast(&Point3::new(c.x, c.y, -100.0), &Vector3::z(), 1e4)
            .unwrap();
        assert!(matches!(
            hit.surface,
            Surface::Box {
                face: Face::Top,
                ..
            }
        ));
        assert!((hit.p_world.z - b.min.z).abs() < 1e-9);
        // Horizontally into a wall from the south.
        let hit = w
            .ray_cast(
                &Point3::new(b.min.x - 1.0, c.y, -1.0),
                &Vector3::x(),
                0.9 + (b.max.x - b.min.x),
            )
            .unwrap();
        assert!(
            matches!(
                hit.surface,
                Surface::Box {
                    face: Face::NegX,
                    ..
                }
            ),
            "{hit:?}"
        );
        assert!((hit.t - 1.0).abs() < 1e-9);
    }

    #[test]
    fn ground_in_the_shadow_of_a_box_is_darker() {
        let w = World::generate_with(2, &WorldParams::small()).unwrap();
        let mut rng = StdRng::seed_from_u64(4);
        let (mut shade, mut n_shade, mut lit, mut n_lit) = (0.0, 0, 0.0, 0);
        for _ in 0..20_000 {
            let x = rng.random_range(-100.0..100.0);
            let y = rng.random_range(-100.0..100.0);
            if w.height_at(x, y) > 0.0 {
                continue;
            }
            // Lit if the ray towards the sun from just above the ground escapes.
            let blocked = w
                .ray_cast(&Point3::new(x, y, -0.01), &w.sun_dir, 1e4)
                .is_some();
            // Average over a small footprint (lod of 0.5 m) to see the baked light, not detail.
            let v = w.ground_value(x as f32, y as f32, -1.0) as f64;
            if blocked {
                shade += v;
                n_shade += 1;
            } else {
                lit += v;
                n_lit += 1;
            }
        }
        assert!(n_shade > 500 && n_lit > 500, "{n_shade} {n_lit}");
        let (shade, lit) = (shade / n_shade as f64, lit / n_lit as f64);
        let expected = w.params.shadow_factor as f64;
        assert!(
            (shade / lit - expected).abs() < 0.1,
            "shadow {shade} lit {lit}"
        );
    }
}
