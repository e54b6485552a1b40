//! The ground's textures: the town's ground (roads, markings, lots), each
//! kind's own ground (grass, carpark stalls, forest floor) and the foliage.

use nalgebra::Vector3;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::layout::{STALLS, stall_centres};
use super::paint::{bake_shadows, dead_leaves};
use super::params::{WorldKind, WorldParams};
use super::scene::{BoxKind, Road, SceneBox};
use crate::texture::{Canvas, MipTexture};

pub(super) fn ground_texture(
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

/// Metres across one tile of the foliage texture (it repeats: foliage is
/// repetitive).
pub(super) const FOLIAGE_TILE_M: f32 = 2.0;

/// Texels across the foliage tile.
pub(super) const FOLIAGE_TEXELS: usize = 128;

/// The repeating foliage of the trees: leaves 4-20 cm on a 2 m tile.
pub(super) fn foliage_texture(seed: u64) -> MipTexture {
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
