//! The `shotpilot mission` command line: plan to a QGroundControl file,
//! upload and download against the fake autopilot, JSON output.

use crate::{cli_support, link_support};

use link_support::{FakeConfig, HOME, Habit, start_fake};
use tokio_util::sync::CancellationToken;

/// The binary as the other CLI subjects run it, quiet but for warnings.
fn shotpilot() -> std::process::Command {
    let mut c = cli_support::shotpilot();
    c.arg("--log").arg("warn");
    c
}

#[test]
fn plan_writes_a_qgc_file_and_refuses_fence_breaches() -> anyhow::Result<()> {
    let dir = tempfile::tempdir()?;
    let file = dir.path().join("shot.plan");
    let out = shotpilot()
        .args([
            "mission",
            "plan",
            "--target",
            "47.3980,8.5458,25,-90,-30",
            "--photo",
            "--home",
            "47.397742,8.545594,488",
        ])
        .args(["--flavour", "ardupilot", "--json", "--qgc-plan"])
        .arg(&file)
        .output()?;
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let j: serde_json::Value = serde_json::from_slice(&out.stdout)?;
    assert_eq!(j["items"].as_array().map(Vec::len), Some(5));
    let doc: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&file)?)?;
    assert_eq!(doc["fileType"], "Plan");
    assert_eq!(doc["mission"]["firmwareType"], 3);
    assert_eq!(doc["mission"]["items"].as_array().map(Vec::len), Some(4));
    // 1 km away: outside the 300 m fence
    let out = shotpilot()
        .args([
            "mission",
            "plan",
            "--target",
            "47.4070,8.5458,25,0,-30",
            "--home",
            "47.397742,8.545594,488",
            "--qgc-plan",
        ])
        .arg(dir.path().join("no.plan"))
        .output()?;
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("geofence"), "{err}");
    assert!(!dir.path().join("no.plan").exists());
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn upload_and_download_json() -> anyhow::Result<()> {
    let cancel = CancellationToken::new();
    let (addr, fake) = start_fake(FakeConfig::clean(Habit::ArduPilot), &cancel);
    let url = format!("udpout:{addr}");
    let target = format!("{},{},30,45,-20", HOME.0 + 0.0005, HOME.1 + 0.0005);
    let url2 = url.clone();
    let out = tokio::task::spawn_blocking(move || {
        shotpilot()
            .args([
                "mission", "upload", "--link", &url2, "--target", &target, "--photo", "--json",
            ])
            .output()
    })
    .await??;
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let j: serde_json::Value = serde_json::from_slice(&out.stdout)?;
    assert_eq!(j["result"], "accepted");
    assert_eq!(
        j["items"], 5,
        "ArduPilot from the heartbeat: home + 4 items"
    );
    assert_eq!(j["flavour"], "ardupilot");
    assert_eq!(j["verified"], true);
    assert!(
        j["seconds"]
            .as_f64()
            .is_some_and(|s| (0.0..5.0).contains(&s))
    );
    assert_eq!(j["retries"], 0);
    assert_eq!(fake.lock().expect("lock").uploads, 1);
    let out = tokio::task::spawn_blocking(move || {
        shotpilot()
            .args(["mission", "download", "--link", &url, "--json"])
            .output()
    })
    .await??;
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let j: serde_json::Value = serde_json::from_slice(&out.stdout)?;
    assert_eq!(j["count"], 5);
    assert_eq!(j["items"][1]["command"], 16);
    assert_eq!(j["items"][1]["z"], 30.0);
    cancel.cancel();
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn start_is_an_explicit_operator_action() -> anyhow::Result<()> {
    use mavlink::dialects::common::MavCmd;
    let cancel = CancellationToken::new();
    let (addr, fake) = start_fake(FakeConfig::clean(Habit::Px4), &cancel);
    let url = format!("udpout:{addr}");
    let target = format!("{},{},30,45,-20", HOME.0 + 0.0005, HOME.1 + 0.0005);
    let u = url.clone();
    let out = tokio::task::spawn_blocking(move || {
        shotpilot()
            .args([
                "mission", "upload", "--link", &u, "--target", &target, "--json",
            ])
            .output()
    })
    .await??;
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let operator = |cmds: &[(MavCmd, f32)]| -> Vec<MavCmd> {
        cmds.iter()
            .map(|(c, _)| *c)
            .filter(|c| *c != MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL)
            .collect()
    };
    assert!(
        operator(&fake.lock().expect("lock").commands).is_empty(),
        "an upload never arms, changes mode or starts"
    );
    let out = tokio::task::spawn_blocking(move || {
        shotpilot()
            .args(["mission", "start", "--link", &url, "--arm", "--json"])
            .output()
    })
    .await??;
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let j: serde_json::Value = serde_json::from_slice(&out.stdout)?;
    assert_eq!(j["result"], "started");
    assert_eq!(
        operator(&fake.lock().expect("lock").commands),
        [
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            MavCmd::MAV_CMD_DO_SET_MODE,
            MavCmd::MAV_CMD_MISSION_START
        ]
    );
    cancel.cancel();
    Ok(())
}
