//! Running the `shotpilot` binary as a user does, for the CLI subjects.

use std::process::{Command, Output};

/// The `shotpilot` binary built with the tests, run from the repository's
/// root (where the README's relative paths point).
pub fn shotpilot() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_shotpilot"));
    c.current_dir(crate::repo_root());
    c
}

/// Runs `cmd` to its end and returns its output; fails the test with the
/// command's error output when it exits unsuccessfully.
pub fn run_ok(cmd: &mut Command) -> Output {
    let out = cmd
        .output()
        .unwrap_or_else(|e| panic!("{cmd:?} did not start: {e}"));
    assert!(
        out.status.success(),
        "{cmd:?} exited with {}: {}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    out
}
