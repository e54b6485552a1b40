//! The `shotpilot-sim` binary's log when its output is not a terminal.

use std::io::Read;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// A short run with its stdout (where the log goes) on a pipe: the log
/// lines carry no ANSI escape codes, as the daemon's do not
/// (`tests/suite/cli_newcomer.rs`, `logs_to_a_pipe_carry_no_colour`).
/// `NO_COLOR` is removed from the child's environment so that only the
/// terminal test can keep the colour out.
#[test]
fn logs_to_a_pipe_carry_no_colour() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut child = Command::new(env!("CARGO_BIN_EXE_shotpilot-sim"))
        .args([
            "--mavlink",
            "udpin:127.0.0.1:0",
            "--video-listen",
            "off",
            "--duration",
            "0.2",
            "--capture-dir",
        ])
        .arg(dir.path().join("captures"))
        .current_dir(dir.path())
        .env("RUST_LOG", "info")
        .env_remove("NO_COLOR")
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("start shotpilot-sim");
    let mut stdout = child.stdout.take().expect("piped stdout");
    let reader = std::thread::spawn(move || {
        let mut log = String::new();
        let _ = stdout.read_to_string(&mut log);
        log
    });
    // Polled with a bound: the run itself lasts 0.2 s of simulated time.
    let deadline = Instant::now() + Duration::from_secs(60);
    let status = loop {
        if let Some(status) = child.try_wait().expect("wait for shotpilot-sim") {
            break status;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("shotpilot-sim did not end within 60 s of a 0.2 s run");
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let log = reader.join().expect("the reader thread");
    assert!(status.success(), "shotpilot-sim failed: {status}\n{log}");
    assert!(log.contains(" INFO "), "info lines were logged: {log}");
    assert!(!log.contains('\u{1b}'), "no escape codes: {log:?}");
}
