//! The generated textures with their metric scales: made for a world, the
//! dead-leaves patchwork and detail layers, baked sun shadows, the land beyond.

use nalgebra::Vector3;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::facades::{facade_texture, roof_texture};
use super::ground::{FOLIAGE_TEXELS, FOLIAGE_TILE_M, foliage_texture, ground_texture};
use super::paint::dead_leaves;
use super::params::{WorldKind, WorldParams};
use super::scene::{Road, SceneBox};
use crate::texture::{Canvas, MipTexture};

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

const PHI: f64 = 1.618_033_988_749_895;

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

pub(super) fn make_textures(
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
