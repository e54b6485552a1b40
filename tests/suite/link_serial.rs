//! The link over a serial line: a pty pair from socat, 57600 baud, the fake
//! autopilot on the far end; mission upload through it, and reconnection
//! when the device vanishes and comes back.
//!
//! Needs `socat` (Debian package).

use crate::link_support;

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use link_support::{FakeConfig, FakeState, Habit, run_fake};
use shotpilot::mission::plan::{self, Flavour, Home, Target};
use shotpilot::mission::upload::{self, same_mission};
use shotpilot::vehicle::{self, Params};
use tokio_util::sync::CancellationToken;

/// A socat process that ends with its owner, also when a test fails
/// (a leaked socat would hold the test runner's output pipe open).
struct Socat(Child);

impl Socat {
    /// Ends the process (the device vanishes).
    fn stop(&mut self) -> std::io::Result<()> {
        self.0.kill()?;
        self.0.wait().map(|_| ())
    }
}

impl Drop for Socat {
    fn drop(&mut self) {
        let _ = self.stop();
    }
}

fn socat_pair(dir: &Path) -> anyhow::Result<Socat> {
    let a = dir.join("gcs");
    let b = dir.join("vehicle");
    let child = Socat(
        Command::new("socat")
            .arg(format!("pty,raw,echo=0,link={}", a.display()))
            .arg(format!("pty,raw,echo=0,link={}", b.display()))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()?,
    );
    for _ in 0..100 {
        if a.exists() && b.exists() {
            return Ok(child);
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    anyhow::bail!("socat did not create the pty pair")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs socat"]
async fn upload_over_pty_at_57600_and_reconnect() -> anyhow::Result<()> {
    let dir = tempfile::tempdir()?;
    let mut socat = socat_pair(dir.path())?;
    let vehicle_dev = dir.path().join("vehicle");
    let gcs_dev = dir.path().join("gcs");
    let cancel = CancellationToken::new();
    let state = std::sync::Arc::new(std::sync::Mutex::new(FakeState::default()));
    let fake_url = format!("serial:{}:57600", vehicle_dev.display());
    tokio::spawn(run_fake(
        fake_url.clone(),
        FakeConfig::clean(Habit::Px4),
        state.clone(),
        cancel.child_token(),
    ));

    let p = Params {
        url: format!("serial:{}:57600", gcs_dev.display()),
        reconnect_min_ms: 100,
        reconnect_max_ms: 500,
        link_lost_after_ms: 2000,
        ..Params::default()
    };
    let (link, _task) = vehicle::spawn(p, upload::Params::default(), cancel.clone())?;
    let v = link.wait_for_vehicle(Duration::from_secs(5)).await?;
    assert_eq!(v.flavour, Some(Flavour::Px4));
    assert_eq!(v.connections, 1);
    let home = Home {
        lat_deg: 47.397742,
        lon_deg: 8.545594,
        alt_amsl_m: 488.0,
    };
    let t = Target {
        lat_deg: 47.3980,
        lon_deg: 8.5458,
        alt_m: 15.0,
        yaw_deg: 10.0,
        gimbal_pitch_deg: -60.0,
        photo: true,
    };
    let items = plan::plan(&t, &home, Flavour::Px4, &plan::Params::default())?;
    let r = link.upload_mission(items.clone()).await?;
    let d = link.download_mission().await?;
    assert!(same_mission(&items, &d.items, false));
    println!(
        "serial pty 57600: upload of {} items {:.2} ms, download {:.2} ms",
        r.items,
        r.seconds * 1e3,
        d.seconds * 1e3
    );

    // the device vanishes ...
    socat.stop()?;
    let mut rx = link.telemetry.vehicle.clone();
    tokio::time::timeout(Duration::from_secs(5), rx.wait_for(|v| !v.connected)).await??;
    // ... and comes back under the same name, with a new vehicle process on it
    let mut socat = socat_pair(dir.path())?;
    tokio::spawn(run_fake(
        fake_url,
        FakeConfig::clean(Habit::Px4),
        state,
        cancel.child_token(),
    ));
    let v = tokio::time::timeout(
        Duration::from_secs(8),
        rx.wait_for(|v| v.connected && v.connections >= 2 && !v.link_lost),
    )
    .await??
    .clone();
    assert!(v.connections >= 2);
    // the same mission again over the new connection (PX4's is five items:
    // gimbal control taken, pitch, waypoint, photo, control released)
    let n = items.len();
    let r = link.upload_mission(items).await?;
    assert_eq!(usize::from(r.items), n);
    cancel.cancel();
    socat.stop()?;
    Ok(())
}
