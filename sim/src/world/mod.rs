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
//!
//! # Files
//!
//! `params` the kinds and parameters; `scene` the boxes, roads, movers and
//! water; `layout` where each kind puts them; `textures`, `ground` and
//! `facades` the textures, `paint` what they share. This file holds the
//! [`World`]: generated, ray cast, shaded.

mod facades;
mod ground;
mod layout;
mod paint;
mod params;
mod scene;
mod textures;

use nalgebra::{Point3, Vector3};
use rand::SeedableRng;
use rand::rngs::StdRng;

use crate::texture::MipTexture;

use self::layout::layout_kind;
use self::textures::make_textures;

pub use params::{WorldError, WorldKind, WorldParams};
pub use scene::{BoxKind, Face, Hit, Mover, Road, SceneBox, Surface, WaterBody};
pub(crate) use textures::Textures;

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

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng;

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
