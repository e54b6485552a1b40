//! What the textures share: the dead-leaves patchwork of random shapes and the
//! buildings' sun shadows baked into a canvas.

use super::params::WorldParams;
use super::scene::SceneBox;
use crate::texture::Canvas;
use nalgebra::Vector3;
use rand::Rng;
use rand::rngs::StdRng;

/// Log-uniform sample in [lo, hi].
fn log_uniform(rng: &mut StdRng, lo: f32, hi: f32) -> f32 {
    lo * (hi / lo).powf(rng.random::<f32>())
}

/// Paints a "dead leaves" patchwork of `count` shapes sized `lo..hi` texels.
pub(super) fn dead_leaves(
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

/// Darkens ground texels from which the ray towards the sun hits a box.
pub(super) fn bake_shadows(
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
