//! The `ideal` realism preset renders exactly what the simulator rendered
//! before realism existed: frames of the default world (seed 5, the CI's
//! SLAM render) along the explore path, with and without sensor noise, and
//! the frames the `render` command writes, hash to the values recorded
//! from `main` (commit 4855b68) before any realism code was added. A change
//! to any of these hashes breaks the comparability of every figure measured
//! on `ideal` so far.

use std::sync::Arc;

use shotpilot_sim::camera::SimCamera;
use shotpilot_sim::dataset::render_path_dataset;
use shotpilot_sim::paths::{CameraPath, Params as PathParams, PathSpec};
use shotpilot_sim::render::{RenderParams, Renderer};
use shotpilot_sim::world::{World, WorldParams};

/// FNV-1a, 64 bit, over the pixel bytes.
fn fnv1a(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// Hashes recorded on `main` (4855b68): default world, seed 5, explore
/// path at these times, noise-free then noisy with seed `1000 + i`.
const EXPLORE_TIMES: [f64; 4] = [0.0, 17.5, 44.0, 81.25];
const MAIN_CLEAN: [u64; 4] = [
    0x5591_e798_6fe9_6f8d,
    0x5b40_1d5e_b79c_b6d1,
    0x9c53_e482_99f7_b2b2,
    0xa76d_a75a_7598_a6fe,
];
const MAIN_NOISY: [u64; 4] = [
    0x9438_0cb8_85fd_21c9,
    0x15b1_7dac_16e0_1209,
    0x7c4a_5f59_015e_ff56,
    0xa5ba_8029_66d7_843e,
];
/// Hashes of the three frames `render_path_dataset` writes for the small
/// world (seed 3) on the orbit path, decoded from their PNG files.
const MAIN_DATASET: [u64; 3] = [
    0x1e22_a753_24cf_ec98,
    0x4856_5fb2_5ed0_f01e,
    0x8dec_68e5_d58e_b67d,
];

#[test]
fn ideal_renders_match_the_hashes_recorded_on_main() {
    let world = Arc::new(World::generate(5));
    let path = CameraPath::explore(&world, PathParams::default());
    let renderer = Renderer::new(world, SimCamera::default(), RenderParams::default());
    let mut clean = [0u64; 4];
    let mut noisy = [0u64; 4];
    for (i, &t) in EXPLORE_TIMES.iter().enumerate() {
        let wfc = path.world_from_cam(t);
        clean[i] = fnv1a(renderer.render(&wfc).as_raw());
        noisy[i] = fnv1a(renderer.render_noisy(&wfc, 1000 + i as u64).as_raw());
    }
    let dir = tempfile::tempdir().unwrap();
    let small = Arc::new(World::generate_with(3, &WorldParams::small()).unwrap());
    let orbit = CameraPath::orbit(PathParams::default());
    let r2 = Renderer::new(small, SimCamera::default(), RenderParams::default());
    render_path_dataset(&r2, &orbit, 3, dir.path(), 3, &PathSpec::Orbit).unwrap();
    let mut dataset = [0u64; 3];
    for (i, t) in [0.0, 30.0, 60.0].iter().enumerate() {
        let img = image::open(dir.path().join(format!("rgb/{t:.6}.png")))
            .unwrap()
            .to_luma8();
        dataset[i] = fnv1a(img.as_raw());
    }
    eprintln!("clean {clean:#018x?}\nnoisy {noisy:#018x?}\ndataset {dataset:#018x?}");
    assert_eq!(clean, MAIN_CLEAN, "noise-free ideal frames changed");
    assert_eq!(noisy, MAIN_NOISY, "noisy ideal frames changed");
    assert_eq!(dataset, MAIN_DATASET, "ideal dataset frames changed");
}
