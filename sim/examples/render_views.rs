//! Renders a few characteristic views of the default world to PNG files,
//! with the time each took: `cargo run --release -p shotpilot-sim --example render_views -- OUT_DIR [SEED]`.

use std::sync::Arc;
use std::time::Instant;

use nalgebra::{Isometry3, Matrix3, Point3, Translation3, UnitQuaternion, Vector3};
use shotpilot_sim::camera::SimCamera;
use shotpilot_sim::render::{RenderParams, Renderer};
use shotpilot_sim::world::World;

fn look_at(eye: Point3<f64>, target: Point3<f64>) -> Isometry3<f64> {
    let f = (target - eye).normalize();
    let right = Vector3::z().cross(&f).normalize();
    let down = f.cross(&right);
    let q = UnitQuaternion::from_matrix(&Matrix3::from_columns(&[right, down, f]));
    Isometry3::from_parts(Translation3::from(eye.coords), q)
}

/// CPU time of this thread, nanoseconds (Linux schedstat), if available.
fn thread_cpu_ns() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    s.split_whitespace().next()?.parse().ok()
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .init();
    let args: Vec<String> = std::env::args().collect();
    let out = std::path::PathBuf::from(args.get(1).map(String::as_str).unwrap_or("/tmp/sim_views"));
    let seed: u64 = args.get(2).map(|s| s.parse()).transpose()?.unwrap_or(1);
    std::fs::create_dir_all(&out)?;
    let t0 = Instant::now();
    let world = Arc::new(World::generate(seed));
    println!(
        "world generated in {:.2} s, {} boxes",
        t0.elapsed().as_secs_f64(),
        world.boxes.len()
    );
    let t0 = Instant::now();
    let params = RenderParams {
        edge_antialias: std::env::var("SIM_NO_AA").is_err(),
        ..RenderParams::default()
    };
    let renderer = Renderer::new(world, SimCamera::default(), params);
    println!("renderer prepared in {:.2} s", t0.elapsed().as_secs_f64());
    let mut views = vec![
        (
            "top_60m",
            Point3::new(0.0, 0.0, -60.0),
            Point3::new(0.1, 0.0, 0.0),
        ),
        (
            "oblique_30m",
            Point3::new(-70.0, -20.0, -30.0),
            Point3::new(0.0, 0.0, 0.0),
        ),
        (
            "oblique_15m",
            Point3::new(-30.0, 10.0, -15.0),
            Point3::new(0.0, 0.0, 0.0),
        ),
        (
            "low_2m",
            Point3::new(0.0, 0.0, -2.0),
            Point3::new(2.0, 0.5, 0.0),
        ),
        (
            "down_2m",
            Point3::new(3.0, 2.0, -2.0),
            Point3::new(3.1, 2.0, 0.0),
        ),
        (
            "street_5m",
            Point3::new(-5.0, -5.0, -5.0),
            Point3::new(60.0, 20.0, -8.0),
        ),
        (
            "sky",
            Point3::new(0.0, 0.0, -50.0),
            Point3::new(1.0, 0.0, -100.0),
        ),
        (
            "high_far",
            Point3::new(-150.0, -100.0, -60.0),
            Point3::new(0.0, 0.0, 0.0),
        ),
    ];
    // Facade close-ups: 2 m and 5 m in front of the tallest building's south wall.
    if let Some(b) = renderer
        .world()
        .boxes
        .iter()
        .filter(|b| b.kind == shotpilot_sim::world::BoxKind::Building)
        .max_by(|a, b| a.height().total_cmp(&b.height()))
    {
        let y = 0.5 * (b.min.y + b.max.y);
        let z = 0.5 * b.min.z;
        for (name, d) in [("wall_2m", 2.0), ("wall_5m", 5.0)] {
            views.push((
                name,
                Point3::new(b.min.x - d, y, z),
                Point3::new(b.min.x, y + 0.3, z + 0.2),
            ));
        }
    }
    let only = std::env::var("SIM_VIEW").ok();
    for (name, eye, target) in views {
        if only.as_deref().is_some_and(|o| o != name) {
            continue;
        }
        let pose = look_at(eye, target);
        let img = renderer.render_noisy(&pose, 7);
        let centre_hit = renderer.world().ray_cast(
            &Point3::from(pose.translation.vector),
            &(pose.rotation * Vector3::z()),
            1e4,
        );
        let dist = centre_hit.map_or(f64::INFINITY, |h| h.t);
        let reps = if only.is_some() { 100 } else { 10 };
        let c0 = thread_cpu_ns();
        let t0 = Instant::now();
        for _ in 0..reps {
            std::hint::black_box(renderer.render_noisy(&pose, 7));
        }
        let ms = t0.elapsed().as_secs_f64() * 1e3 / reps as f64;
        let cpu_ms = c0
            .zip(thread_cpu_ns())
            .map_or(f64::NAN, |(a, b)| (b - a) as f64 * 1e-6 / reps as f64);
        img.save(out.join(format!("{name}.png")))?;
        println!(
            "{name}: {ms:.1} ms wall, {cpu_ms:.1} ms cpu per frame, centre ray hits at {dist:.1} m"
        );
    }
    Ok(())
}
