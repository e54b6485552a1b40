//! Every world kind renders and is what it says: the town as before, open
//! grass with little texture, a car park of identical cars, a wood of
//! identical trees, lakes whose surface changes from moment to moment,
//! traffic that drives, and identical buildings around a car park.

use std::sync::Arc;

use image::GrayImage;
use nalgebra::{Isometry3, Point3};
use shotpilot_sim::camera::SimCamera;
use shotpilot_sim::paths::{CameraPath, Params as PathParams, camera_from_yaw_pitch};
use shotpilot_sim::render::{RenderParams, Renderer, SceneState};
use shotpilot_sim::world::{BoxKind, SceneBox, World, WorldKind, WorldParams};

fn world(kind: WorldKind) -> Arc<World> {
    Arc::new(
        World::generate_with(
            5,
            &WorldParams {
                kind,
                ..WorldParams::small()
            },
        )
        .unwrap(),
    )
}

fn clean(world: Arc<World>) -> Renderer {
    Renderer::new(
        world,
        SimCamera::default(),
        RenderParams {
            noise_sigma: 0.0,
            ..RenderParams::default()
        },
    )
}

fn render_at(r: &Renderer, pose: &Isometry3<f64>, t: f64) -> GrayImage {
    let mut buf = Vec::new();
    r.render_scene(
        std::slice::from_ref(pose),
        &SceneState { time_s: t },
        &mut buf,
    )
    .unwrap();
    GrayImage::from_raw(
        640,
        480,
        buf.iter()
            .map(|v| v.round().clamp(0.0, 255.0) as u8)
            .collect(),
    )
    .unwrap()
}

/// Mean absolute horizontal gradient: how much texture a view has.
fn texture_energy(img: &GrayImage) -> f64 {
    let mut sum = 0.0;
    for y in 0..img.height() {
        for x in 0..img.width() - 1 {
            sum += (img.get_pixel(x + 1, y).0[0] as f64 - img.get_pixel(x, y).0[0] as f64).abs();
        }
    }
    sum / (img.width() * img.height()) as f64
}

fn down_on(x: f64, y: f64, altitude: f64) -> Isometry3<f64> {
    camera_from_yaw_pitch(Point3::new(x, y, -altitude), 0.0, 90f64.to_radians())
}

/// The boxes of `kind` look alike: same size, same texture offsets, box-local texture.
fn identical(boxes: &[&SceneBox]) -> bool {
    let a = boxes[0];
    boxes.iter().all(|b| {
        (b.max - b.min - (a.max - a.min)).norm() < 1e-9
            && b.facade_offset == a.facade_offset
            && b.roof_offset == a.roof_offset
            && b.albedo == a.albedo
            && b.local_texture
    })
}

/// Renders straight down over the centres of two boxes from the same
/// height above them and compares the crops covering the boxes.
fn same_look(r: &Renderer, a: &SceneBox, b: &SceneBox, altitude: f64, half: (u32, u32)) -> bool {
    let centre = |s: &SceneBox| ((s.min + s.max) * 0.5, s.min.z);
    let (ca, za) = centre(a);
    let (cb, zb) = centre(b);
    let ia = render_at(r, &down_on(ca.x, ca.y, altitude - za), 0.0);
    let ib = render_at(r, &down_on(cb.x, cb.y, altitude - zb), 0.0);
    let crop = |img: &GrayImage| {
        image::imageops::crop_imm(img, 320 - half.0, 240 - half.1, 2 * half.0, 2 * half.1)
            .to_image()
    };
    let (pa, pb) = (crop(&ia), crop(&ib));
    let diff = pa
        .as_raw()
        .iter()
        .zip(pb.as_raw())
        .map(|(x, y)| (*x as i32 - *y as i32).abs())
        .max()
        .unwrap_or(255);
    diff <= 1
}

#[test]
fn world_names_parse_and_the_town_is_unchanged() {
    for k in WorldKind::ALL {
        assert_eq!(k.name().parse::<WorldKind>().unwrap(), k);
    }
    assert!("moon".parse::<WorldKind>().is_err());
    let town = World::generate_with(5, &WorldParams::tiny()).unwrap();
    let default = World::generate_with(
        5,
        &WorldParams {
            kind: WorldKind::Town,
            ..WorldParams::tiny()
        },
    )
    .unwrap();
    assert_eq!(town.boxes, default.boxes);
    assert!(town.movers.is_empty() && town.water.is_empty());
}

#[test]
fn grass_has_far_less_texture_than_the_town() {
    let path_pose = |w: &World| CameraPath::explore(w, PathParams::default()).world_from_cam(30.0);
    let town = world(WorldKind::Town);
    let grass = world(WorldKind::Grass);
    assert!(grass.boxes.iter().all(|b| b.kind != BoxKind::Building));
    let et = texture_energy(&render_at(&clean(town.clone()), &path_pose(&town), 0.0));
    let eg = texture_energy(&render_at(&clean(grass.clone()), &path_pose(&grass), 0.0));
    eprintln!("texture energy: town {et:.2}, grass {eg:.2}");
    assert!(eg < 0.35 * et, "grass {eg} town {et}");
    assert!(eg > 0.2, "grass is not blank: {eg}");
}

#[test]
fn carpark_cars_are_identical_and_look_identical() {
    let w = world(WorldKind::Carpark);
    let cars: Vec<&SceneBox> = w.boxes.iter().filter(|b| b.kind == BoxKind::Car).collect();
    assert!(cars.len() > 300, "{} cars", cars.len());
    assert!(identical(&cars));
    let r = clean(w.clone());
    // Two cars far apart, seen from 6 m above their roofs: the crop over the car is the same.
    let (a, b) = (cars[3], cars[cars.len() - 5]);
    assert!(((a.min + a.max) * 0.5 - (b.min + b.max) * 0.5).norm() > 50.0);
    assert!(same_look(&r, a, b, 6.0, (60, 130)));
}

#[test]
fn trees_are_identical_crowns_of_repeating_foliage() {
    let w = world(WorldKind::Trees);
    let crowns: Vec<&SceneBox> = w.boxes.iter().filter(|b| b.kind == BoxKind::Tree).collect();
    assert!(crowns.len() > 400, "{} trees", crowns.len());
    assert!(
        crowns.iter().all(|c| c.max.z < -2.0),
        "crowns stand on trunks"
    );
    let sizes_equal = crowns
        .iter()
        .all(|c| ((c.max - c.min) - (crowns[0].max - crowns[0].min)).norm() < 1e-9);
    assert!(sizes_equal);
    let r = clean(w.clone());
    assert!(same_look(
        &r,
        crowns[10],
        crowns[crowns.len() - 10],
        6.0,
        (100, 100)
    ));
}

#[test]
fn water_changes_from_moment_to_moment_and_the_land_does_not() {
    let w = world(WorldKind::Water);
    assert_eq!(w.water.len(), 2);
    let r = clean(w.clone());
    // Over the shore: land in the middle, water left and right (image x is east... the lakes are north and south).
    let pose = camera_from_yaw_pitch(Point3::new(0.0, 20.0, -25.0), 0.0, 60f64.to_radians());
    let a = render_at(&r, &pose, 10.0);
    let b = render_at(&r, &pose, 10.5);
    // Classify pixels by where their ray meets the ground.
    let (mut water_diff, mut nw, mut land_diff, mut nl) = (0.0, 0, 0.0, 0);
    for y in (0..480).step_by(3) {
        for x in (0..640).step_by(3) {
            let Some(ray) = r.pixel_ray(x, y) else {
                continue;
            };
            let d =
                pose.rotation * nalgebra::Vector3::new(ray[0] as f64, ray[1] as f64, ray[2] as f64);
            let Some(hit) = w.ray_cast(&Point3::from(pose.translation.vector), &d, 500.0) else {
                continue;
            };
            let diff = (a.get_pixel(x as u32, y as u32).0[0] as f64
                - b.get_pixel(x as u32, y as u32).0[0] as f64)
                .abs();
            let on_water = matches!(hit.surface, shotpilot_sim::world::Surface::Ground)
                && w.water.iter().any(|l| {
                    hit.p_world.x >= l.min[0]
                        && hit.p_world.x <= l.max[0]
                        && hit.p_world.y >= l.min[1]
                        && hit.p_world.y <= l.max[1]
                });
            if on_water {
                water_diff += diff;
                nw += 1;
            } else {
                land_diff += diff;
                nl += 1;
            }
        }
    }
    let (water_diff, land_diff) = (water_diff / nw as f64, land_diff / nl as f64);
    eprintln!(
        "half a second apart: water changes {water_diff:.2}, land {land_diff:.3} grey levels ({nw} / {nl} samples)"
    );
    assert!(nw > 1000 && nl > 1000);
    assert!(water_diff > 2.0, "{water_diff}");
    assert_eq!(land_diff, 0.0);
}

#[test]
fn traffic_drives_along_the_roads() {
    let town = world(WorldKind::Town);
    let traffic = world(WorldKind::Traffic);
    assert_eq!(town.boxes, traffic.boxes, "the same town at time 0");
    assert!(
        traffic.movers.len() >= 10,
        "{} movers",
        traffic.movers.len()
    );
    let (t0, t1) = (traffic.boxes_at(0.0), traffic.boxes_at(1.0));
    for m in &traffic.movers {
        let axis = if m.along_x { 0 } else { 1 };
        let moved = t1[m.index].min[axis] - t0[m.index].min[axis];
        let wrapped = (moved.abs() - (m.hi - m.lo)).abs() < 20.0;
        assert!(
            (moved - m.speed_m_s).abs() < 1e-9 || wrapped,
            "car {} moved {moved} at {} m/s",
            m.index,
            m.speed_m_s
        );
        assert!((5.0..=14.0).contains(&m.speed_m_s.abs()));
        assert_eq!(traffic.boxes[m.index].kind, BoxKind::Car);
    }
    // A render changes where cars drive.
    let r = clean(traffic.clone());
    let pose = CameraPath::explore(&traffic, PathParams::default()).world_from_cam(20.0);
    assert_ne!(render_at(&r, &pose, 0.0), render_at(&r, &pose, 0.5));
}

#[test]
fn aliasing_world_repeats_identical_buildings_around_identical_cars() {
    let w = world(WorldKind::Aliasing);
    let buildings: Vec<&SceneBox> = w
        .boxes
        .iter()
        .filter(|b| b.kind == BoxKind::Building)
        .collect();
    let cars: Vec<&SceneBox> = w.boxes.iter().filter(|b| b.kind == BoxKind::Car).collect();
    assert!(buildings.len() >= 20, "{} buildings", buildings.len());
    assert!(cars.len() >= 100, "{} cars", cars.len());
    assert!(identical(&buildings) && identical(&cars));
    let r = clean(w.clone());
    assert!(same_look(
        &r,
        buildings[0],
        buildings[buildings.len() - 1],
        12.0,
        (150, 110)
    ));
}

#[test]
fn ideal_captures_of_a_moving_world_follow_scene_time() {
    use shotpilot_sim::imaging::Imager;
    use shotpilot_sim::realism::Realism;
    let ideal = Realism::ideal();
    let capture = |kind: WorldKind, t: f64| {
        let w = world(kind);
        let pose = CameraPath::explore(&w, PathParams::default()).world_from_cam(20.0);
        let mut imager = Imager::new(Arc::new(clean(w)), ideal.camera.clone(), &ideal.lighting);
        imager.capture(t, &|_| pose, None).unwrap().image
    };
    // The datasets and the live simulator expose through the imager: with
    // every effect off, cars still drive and water still moves.
    assert_ne!(
        capture(WorldKind::Traffic, 0.0),
        capture(WorldKind::Traffic, 0.5)
    );
    assert_ne!(
        capture(WorldKind::Water, 0.0),
        capture(WorldKind::Water, 0.5)
    );
    assert_eq!(capture(WorldKind::Town, 0.0), capture(WorldKind::Town, 0.5));
}
