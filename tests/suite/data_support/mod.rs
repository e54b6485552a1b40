//! Where the tests find the real sequences of `../shared/data`.
//!
//! On a machine without them the real-data tests say "skipped" and pass, so
//! the plain `cargo test` works anywhere. `.ci/run` sets
//! `SHOTPILOT_REQUIRE_DATA=1`: there a missing sequence fails the test
//! instead of letting an accuracy check pass unseen.
#![allow(dead_code)] // each test binary uses its own subset

use std::path::PathBuf;

/// The shared data directory, or the sequence `name` inside it (`""`: the
/// directory itself). Looked up in `SHOTPILOT_DATA`, then `../shared/data`
/// and `../../shared/data` from the crate (a worktree one level deeper).
/// `None` (with a "skipped" line) when absent, unless
/// `SHOTPILOT_REQUIRE_DATA` is set to anything but `0`: then it panics.
pub fn shared_data(name: &str) -> Option<PathBuf> {
    let root = crate::repo_root();
    let mut dirs: Vec<PathBuf> = std::env::var_os("SHOTPILOT_DATA")
        .map(PathBuf::from)
        .into_iter()
        .collect();
    dirs.extend(["../shared/data", "../../shared/data"].map(|r| root.join(r)));
    if let Some(found) = dirs.iter().map(|d| d.join(name)).find(|p| p.is_dir()) {
        return Some(found);
    }
    let required = std::env::var("SHOTPILOT_REQUIRE_DATA").is_ok_and(|v| !v.is_empty() && v != "0");
    assert!(
        !required,
        "SHOTPILOT_REQUIRE_DATA is set but {name:?} is in none of {dirs:?}"
    );
    eprintln!("skipped: ../shared/data/{name} not present");
    None
}
