//! `shotpilot vocab` as a user runs it: train on an image folder and on a
//! dataset, import a DBoW2 text vocabulary, describe a file, and fail with a
//! clear message on a corrupt one.

use crate::data_support;

use crate::cli_support::shotpilot;

use image::{GrayImage, Luma};
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use shotpilot::bow::Vocabulary;

fn run_json(args: &[&str]) -> serde_json::Value {
    let out = shotpilot().args(args).output().unwrap();
    assert!(
        out.status.success(),
        "{args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8(out.stdout).unwrap();
    assert_eq!(stdout.trim().lines().count(), 1, "{stdout}");
    serde_json::from_str(&stdout).unwrap()
}

/// A 320x240 image of random grey rectangles (plenty of FAST corners).
fn blocks(seed: u64) -> GrayImage {
    let mut rng = SmallRng::seed_from_u64(seed);
    let mut img = GrayImage::from_pixel(320, 240, Luma([128]));
    for _ in 0..60 {
        let (x0, y0) = (rng.random_range(0..300u32), rng.random_range(0..220u32));
        let (w, h) = (rng.random_range(8..60u32), rng.random_range(8..60u32));
        let v = rng.random::<u8>();
        for y in y0..(y0 + h).min(240) {
            for x in x0..(x0 + w).min(320) {
                img.put_pixel(x, y, Luma([v]));
            }
        }
    }
    img
}

#[test]
fn train_on_an_image_folder_then_info() {
    let dir = tempfile::tempdir().unwrap();
    let imgs = dir.path().join("imgs");
    std::fs::create_dir(&imgs).unwrap();
    for i in 0..6 {
        blocks(i).save(imgs.join(format!("{i:03}.png"))).unwrap();
    }
    std::fs::write(imgs.join("notes.txt"), "not an image").unwrap();
    let out = dir.path().join("v.bowvoc");
    let v = run_json(&[
        "vocab",
        "train",
        imgs.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--k",
        "5",
        "--levels",
        "3",
        "--features",
        "300",
        "--seed",
        "7",
        "--json",
    ]);
    assert_eq!(v["images"].as_u64(), Some(6), "{v}");
    assert_eq!((v["k"].as_u64(), v["levels"].as_u64()), (Some(5), Some(3)));
    let descriptors = v["descriptors"].as_u64().unwrap();
    assert!(descriptors > 6 * 150, "{v}");
    let words = v["words"].as_u64().unwrap();
    assert!(words > 25 && words <= 125, "{v}");
    let voc = Vocabulary::load(&out).unwrap();
    assert_eq!(voc.word_count() as u64, words);
    assert_eq!(
        std::fs::metadata(&out).unwrap().len(),
        v["file_bytes"].as_u64().unwrap()
    );

    // Same seed, same file.
    let out2 = dir.path().join("v2.bowvoc");
    let args = [
        "vocab",
        "train",
        imgs.to_str().unwrap(),
        "--out",
        out2.to_str().unwrap(),
        "--k",
        "5",
        "--levels",
        "3",
        "--features",
        "300",
        "--seed",
        "7",
        "--json",
    ];
    run_json(&args);
    assert_eq!(std::fs::read(&out).unwrap(), std::fs::read(&out2).unwrap());

    let info = run_json(&["vocab", "info", out.to_str().unwrap(), "--json"]);
    assert_eq!(info["words"].as_u64(), Some(words));
    assert_eq!(info["weighting"].as_str(), Some("TfIdf"));

    // One flipped byte: a clear error, non-zero exit.
    let mut bytes = std::fs::read(&out).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0x40;
    std::fs::write(&out, bytes).unwrap();
    let o = shotpilot()
        .args(["vocab", "info", out.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("checksum"), "{err}");
}

#[test]
fn import_a_dbow2_text_vocabulary() {
    let dir = tempfile::tempdir().unwrap();
    let txt = dir.path().join("voc.txt");
    // k = 3, L = 1: three leaves.
    let line = |b: u8, w: f32| format!("0 1 {} {w}\n", vec![b.to_string(); 32].join(" "));
    let text = format!(
        "3 1 0 0\n{}{}{}",
        line(0, 0.5),
        line(255, 1.0),
        line(15, 2.0)
    );
    std::fs::write(&txt, text).unwrap();
    let out = dir.path().join("voc.bowvoc");
    let v = run_json(&[
        "vocab",
        "import",
        txt.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--json",
    ]);
    assert_eq!(
        (v["nodes"].as_u64(), v["words"].as_u64()),
        (Some(4), Some(3)),
        "{v}"
    );
    let voc = Vocabulary::load(&out).unwrap();
    assert_eq!(voc.word_of(&[0x0f0f_0f0f_0f0f_0f0f; 4]).1, 2.0);

    // A malformed line is named.
    std::fs::write(&txt, "3 1 0 0\n0 1 1 2 3\n").unwrap();
    let o = shotpilot()
        .args([
            "vocab",
            "import",
            txt.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("line 2"));
}

#[test]
fn train_on_a_dataset() {
    let Some(teddy) = data_support::shared_data("tum_fr3_teddy_100") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("teddy.bowvoc");
    let v = run_json(&[
        "vocab",
        "train",
        teddy.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--every",
        "10",
        "--k",
        "6",
        "--levels",
        "3",
        "--json",
    ]);
    assert_eq!(v["images"].as_u64(), Some(10), "{v}");
    assert!(v["descriptors"].as_u64().unwrap() > 9000, "{v}");
    assert!(Vocabulary::load(&out).is_ok());
}
