//! The scene's pieces: boxes (buildings, vehicles, containers, kiosks) and their
//! faces, surfaces and ray hits, roads, movers, open water.

use nalgebra::{Point3, Vector3};

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
