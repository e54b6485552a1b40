//! What a newcomer tripped over on the command line, each pinned: `mission
//! plan` says in its usage that it needs `--home`; an error prints each
//! cause once; logs written to a pipe carry no ANSI colour codes; the
//! `slam` summary's posed-frame count agrees with its ATE line.

use crate::cli_support::{run_ok, shotpilot};
use crate::data_support;

use std::io::{BufRead, BufReader, Read};
use std::process::{Command, Stdio};

#[test]
fn mission_plan_usage_requires_home() {
    let help = shotpilot()
        .args(["mission", "plan", "--help"])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&help.stdout);
    let usage = text
        .lines()
        .find(|l| l.starts_with("Usage:"))
        .expect("a usage line");
    assert!(usage.contains(" --home <LAT,LON,ALT_AMSL>"), "{usage}");
    assert!(!usage.contains("[--home"), "not optional: {usage}");
    // Without it: refused by the parser, naming it.
    let out = shotpilot()
        .args([
            "mission",
            "plan",
            "--target",
            "47.398,8.5458,25,-90,-30",
            "--qgc-plan",
            "/nonexistent/x.plan",
        ])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("required") && err.contains("--home"), "{err}");
}

#[test]
fn an_error_prints_each_cause_once() {
    let out = shotpilot()
        .args(["slam", "/nonexistent/dataset"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    let line = err
        .lines()
        .find(|l| l.starts_with("error: "))
        .expect("an error line");
    let parts: Vec<&str> = line.split(": ").map(str::trim).collect();
    for (i, p) in parts.iter().enumerate() {
        assert!(!parts[i + 1..].contains(p), "{p:?} repeated in {line:?}");
    }
    assert!(line.contains("/nonexistent/dataset"), "{line}");
}

#[test]
fn logs_to_a_pipe_carry_no_colour() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("config.toml");
    std::fs::write(
        &config,
        "[server]\nbind = \"127.0.0.1:0\"\ndata_dir = \"data\"\n\n[sim]\nenabled = false\n\n\
         [slam]\nenabled = false\n\n[video]\nurl = \"http://127.0.0.1:9/video.mjpg\"\n",
    )
    .unwrap();
    let mut child = shotpilot()
        .args(["--log", "info", "run", "--config"])
        .arg(&config)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stderr = BufReader::new(child.stderr.take().unwrap());
    let mut log = String::new();
    // Up to the API's address (logged, and printed), then stop it.
    loop {
        let mut line = String::new();
        if stderr.read_line(&mut line).unwrap() == 0 {
            break;
        }
        log.push_str(&line);
        if line.contains("operator page at") {
            break;
        }
    }
    let _ = Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status();
    stderr.read_to_string(&mut log).unwrap();
    let _ = child.wait();
    assert!(log.contains(" INFO "), "info lines were logged: {log}");
    assert!(!log.contains('\u{1b}'), "no escape codes: {log:?}");
}

#[test]
fn slam_summary_counts_agree_with_the_ate_line() {
    let Some(dir) = data_support::shared_data("tum_fr3_teddy_100") else {
        return;
    };
    let out = run_ok(
        shotpilot()
            .args(["--log", "warn", "slam", "--sequential", "--gt"])
            .arg(dir.join("groundtruth.txt"))
            .arg(&dir),
    );
    let text = String::from_utf8_lossy(&out.stdout);
    let first = text.lines().next().unwrap();
    let ate = text
        .lines()
        .find(|l| l.starts_with("ATE"))
        .expect("an ATE line");
    let num_before = |s: &str, key: &str| -> i64 {
        let i = s.find(key).unwrap_or_else(|| panic!("{key:?} in {s:?}"));
        s[..i]
            .split(|c: char| !c.is_ascii_digit())
            .rfind(|w| !w.is_empty())
            .unwrap()
            .parse()
            .unwrap()
    };
    let posed = num_before(first, " frames posed");
    let tracked = num_before(first, " tracked");
    let optional = |key: &str| {
        if first.contains(key) {
            num_before(first, key)
        } else {
            0
        }
    };
    let at_init = optional(" posed at initialisation");
    let gone = optional(" whose reference keyframe is gone");
    let later = optional(" in maps started after a loss");
    assert_eq!(posed, tracked + at_init - gone - later, "{first}");
    assert!(
        !first.contains("other"),
        "every difference explained: {first}"
    );
    assert_eq!(num_before(ate, " posed frames matched"), posed, "{ate}");
    let keyframes = num_before(first, " keyframes");
    assert_eq!(num_before(ate, " keyframes matched"), keyframes, "{ate}");
}
