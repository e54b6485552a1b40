//! A 1280x720 camera at 30 fps (what a SIYI A8 mini sends): SLAM on the
//! full picture against SLAM on the picture decimated by 2 with the
//! intrinsics scaled to match. The simulator renders the explore flight at
//! 720p, OpenH264 encodes it at 1.5 Mbit/s (one IDR per second), the
//! decode loop hands SLAM the luma at full size or decimated, exactly as
//! the daemon's `[video] downscale` does. Printed: tracked share, ATE, CPU
//! per frame (SLAM thread, mapping inline), decode time per frame.

use std::sync::Arc;
use std::time::Instant;

use shotpilot::camera::Camera;
use shotpilot::eval::{self, Trajectory};
use shotpilot::slam::{self, Slam};
use shotpilot::video::decode_loop::{DecodeLoop, DecodeParams, Decoded};
use shotpilot::video::h264::{AccessUnit, GrayEncoder};
use shotpilot::video::source::decimated_camera;
use shotpilot_sim::camera::SimCamera;
use shotpilot_sim::paths::{CameraPath, Params as PathParams};
use shotpilot_sim::render::{RenderParams, Renderer};
use shotpilot_sim::world::World;

const FPS: f64 = 30.0;
const SECONDS: f64 = 20.0;

fn thread_cpu_ms() -> f64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes the timespec it is given.
    unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    ts.tv_sec as f64 * 1e3 + ts.tv_nsec as f64 / 1e6
}

struct Run {
    tracked: usize,
    frames: usize,
    ate_m: f64,
    length_m: f64,
    cpu_ms_mean: f64,
    cpu_ms_p95: f64,
    decode_ms_mean: f64,
}

fn run(
    aus: &[Vec<u8>],
    gt: &[(f64, nalgebra::Isometry3<f64>)],
    cam: &Camera,
    downscale: u32,
) -> Run {
    let cam = decimated_camera(cam, downscale);
    let mut dl = DecodeLoop::new(DecodeParams {
        downscale,
        ..Default::default()
    })
    .unwrap();
    let mut s = Slam::new(
        cam,
        slam::Params {
            sequential: true,
            ..Default::default()
        },
    )
    .unwrap();
    let (mut cpu, mut dec) = (Vec::new(), Vec::new());
    for (i, a) in aus.iter().enumerate() {
        let t = gt[i].0;
        let au = AccessUnit {
            data: a.clone(),
            capture_time: Some(t),
            received: Instant::now(),
            received_unix: t,
            lost: 0,
            gaps: Vec::new(),
        };
        let c0 = thread_cpu_ms();
        let Decoded::Frame(f) = dl.step(&au, false) else {
            panic!("picture {i} did not decode");
        };
        let c1 = thread_cpu_ms();
        s.process(i as u64, t, f.image.clone());
        cpu.push(thread_cpu_ms() - c1);
        dec.push(c1 - c0);
    }
    let r = s.finish();
    let gt_traj = Trajectory {
        poses: gt
            .iter()
            .map(|(t, p)| eval::StampedPose {
                t: *t,
                world_from_cam: *p,
            })
            .collect(),
    };
    let length_m = gt
        .windows(2)
        .map(|w| (w[1].1.translation.vector - w[0].1.translation.vector).norm())
        .sum();
    let ate = eval::evaluate(&gt_traj, &r.trajectory(), &eval::Params::default()).unwrap();
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let mut sorted = cpu.clone();
    sorted.sort_by(f64::total_cmp);
    Run {
        tracked: r.records.len(),
        frames: aus.len(),
        ate_m: ate.ate.rmse,
        length_m,
        cpu_ms_mean: mean(&cpu),
        cpu_ms_p95: sorted[(sorted.len() * 95 / 100).min(sorted.len() - 1)],
        decode_ms_mean: mean(&dec),
    }
}

#[test]
#[ignore = "slow: renders and encodes 600 frames at 1280x720 (about 2 minutes)"]
fn slam_at_720p_full_versus_decimated() {
    let world = Arc::new(World::generate(5));
    let path = CameraPath::explore(&world, PathParams::default());
    // The simulator's camera (horizontal field of view kept) at 1280x720.
    let sim = SimCamera::default();
    let s = 1280.0 / f64::from(sim.width);
    let cam720 = SimCamera {
        width: 1280,
        height: 720,
        fx: sim.fx * s,
        fy: sim.fy * s,
        cx: 639.5,
        cy: 359.5,
        ..sim
    };
    let renderer = Renderer::new(world, cam720, RenderParams::default());
    let n = (SECONDS * FPS) as usize;
    let gt: Vec<(f64, nalgebra::Isometry3<f64>)> = (0..n)
        .map(|i| {
            let t = i as f64 / FPS;
            (1.7e9 + t, path.world_from_cam(path.start() + t))
        })
        .collect();
    let mut enc = GrayEncoder::new(1280, 720, FPS as f32, 1_500_000, FPS as u32).unwrap();
    let aus: Vec<Vec<u8>> = gt
        .iter()
        .enumerate()
        .map(|(i, (_, p))| enc.encode(&renderer.render_noisy(p, i as u64)).unwrap())
        .collect();
    let cam = shotpilot::simulator::camera_from_sim(&cam720).unwrap();
    for downscale in [1, 2] {
        let r = run(&aus, &gt, &cam, downscale);
        println!(
            "720p at 30 fps, downscale {downscale}: tracked {}/{} ({:.1} %), ATE {:.3} m over {:.1} m ({:.3} %), SLAM CPU per frame mean {:.1} ms p95 {:.1} ms, decode {:.1} ms (budget 33.3 ms per frame)",
            r.tracked,
            r.frames,
            100.0 * r.tracked as f64 / r.frames as f64,
            r.ate_m,
            r.length_m,
            100.0 * r.ate_m / r.length_m,
            r.cpu_ms_mean,
            r.cpu_ms_p95,
            r.decode_ms_mean
        );
        assert!(
            r.tracked as f64 >= 0.8 * r.frames as f64,
            "downscale {downscale}"
        );
        assert!(r.ate_m <= 0.01 * r.length_m, "downscale {downscale}");
    }
}
