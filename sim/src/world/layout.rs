//! Where things stand: the roads and boxes of the town, and each other kind's
//! layout (grass, carpark stalls and cars, trees, a lake's shore, traffic).

use nalgebra::Vector3;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::params::{WorldKind, WorldParams};
use super::scene::{BoxKind, Mover, Road, SceneBox, WaterBody};

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

/// Layout of `params.kind`: roads, boxes, movers, water.
pub(super) fn layout_kind(
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
pub(super) struct StallGrid {
    /// Stall width (along y), m.
    pub(super) width: f64,
    /// Stall depth (along x), m.
    pub(super) depth: f64,
    /// Distance between the centres of two double rows, m.
    pub(super) pitch: f64,
}

pub(super) const STALLS: StallGrid = StallGrid {
    width: 2.5,
    depth: 5.0,
    pitch: 16.5,
};

/// Centres of the stalls within `radius` of home (outside the take-off
/// area), and whether each faces +x.
pub(super) fn stall_centres(radius: f64) -> Vec<(f64, f64, bool)> {
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
