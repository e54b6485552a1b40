//! What a world is made from: its kind (town, grass, carpark, trees, water,
//! traffic, aliasing), its parameters and their presets, and the errors of a
//! bad one.

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

    pub(super) fn validate(&self) -> Result<(), WorldError> {
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

impl WorldKind {
    /// The kind's own texture settings (the town keeps the parameters as
    /// given): smooth surfaces carry less close-up detail.
    pub(super) fn adjust(self, p: &mut WorldParams) {
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
