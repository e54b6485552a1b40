//! The facade and roof atlases (window grids, floor bands, grime; AC units,
//! pipes, vents).

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::paint::dead_leaves;
use super::params::WorldParams;
use crate::texture::{Canvas, MipTexture};

pub(super) fn facade_texture(seed: u64, p: &WorldParams) -> MipTexture {
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

pub(super) fn roof_texture(seed: u64, p: &WorldParams) -> MipTexture {
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
