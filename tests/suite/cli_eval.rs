//! The `shotpilot eval` command as a user runs it: exit codes, one JSON
//! object with `--json`, a PNG with `--plot`, errors that name file and line.

use crate::cli_support::{run_ok, shotpilot};

const GT: &str = "tests/fixtures/teddy_groundtruth.txt";
const EST: &str = "tests/fixtures/teddy_estimate.txt";

#[test]
fn json_is_one_object_with_the_documented_keys() {
    let out = run_ok(shotpilot().args(["eval", "--gt", GT, "--est", EST, "--json"]));
    let stdout = String::from_utf8(out.stdout).unwrap();
    assert_eq!(stdout.trim().lines().count(), 1, "{stdout}");
    let v: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    // The fixture is the ground truth moved by a Sim(3) with scale 0.5 plus
    // 2 mm noise (see its header): the scale comes back, the error is ~noise.
    assert!((v["scale"].as_f64().unwrap() - 0.5).abs() < 0.005, "{v}");
    let rmse = v["ate_rmse_m"].as_f64().unwrap();
    assert!(rmse > 0.0025 && rmse < 0.0040, "{v}");
    assert!(v["ate_max_m"].as_f64().unwrap() >= rmse);
    assert_eq!(v["matched"].as_u64(), Some(100));
}

#[test]
fn plot_writes_a_png() {
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("p.png");
    run_ok(
        shotpilot()
            .args(["eval", "--gt", GT, "--est", EST, "--plot"])
            .arg(&png),
    );
    let img = image::open(&png).unwrap();
    assert_eq!((img.width(), img.height()), (1400, 600));
}

#[test]
fn bad_input_fails_with_file_and_line() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.txt");
    std::fs::write(&bad, "1.0 0 0 0 0 0 0 1\n2.0 0 0 zero 0 0 0 1\n").unwrap();
    let out = shotpilot()
        .args(["eval", "--gt", GT, "--est"])
        .arg(&bad)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("bad.txt:2") && err.contains("zero"), "{err}");
    let out = shotpilot()
        .args(["eval", "--gt", "missing.txt", "--est", EST])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("missing.txt"));
    // Nothing matches within 1 ms (the fixture is shifted by 3 ms).
    let out = shotpilot()
        .args(["eval", "--gt", GT, "--est", EST, "--max-dt", "0.001"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("matched"));
}

#[test]
fn bad_config_names_key_and_line() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("c.toml");
    std::fs::write(&cfg, "[camera]\nwidth = 640\nfocal_length = 3\n").unwrap();
    let out = shotpilot()
        .args(["--config"])
        .arg(&cfg)
        .args(["eval", "--gt", GT, "--est", EST])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("focal_length") && err.contains("line 3"),
        "{err}"
    );
}

#[test]
fn help_and_version() {
    let out = shotpilot().arg("--help").output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("eval") && text.contains("--config"));
    let out = shotpilot().arg("--version").output().unwrap();
    assert!(String::from_utf8_lossy(&out.stdout).starts_with("shotpilot "));
}
