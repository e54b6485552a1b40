//! Wire compatibility with pymavlink, an independent MAVLink implementation:
//! it decodes our heartbeat and mission items, and MAVLink 2 signing works
//! with the right key and fails with a wrong one, in both directions.
//!
//! Needs `pymavlink` in the Python at `$SHOTPILOT_PYTHON` (default
//! `/work/venv/bin/python`, else `python3`).

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use shotpilot::mission::plan::{self, Flavour, Home, Target};
use shotpilot::mission::upload;
use shotpilot::vehicle::{self, LinkError, Params, Signing};
use tokio_util::sync::CancellationToken;

const KEY: &str = "4f2c1b8a9d7e6f5041322314a5b6c7d8e9f00112233445566778899aabbccdde";
const WRONG: &str = "4f2c1b8a9d7e6f5041322314a5b6c7d8e9f00112233445566778899aabbccddf";

/// A running pymavlink vehicle: the process, its stdout, and the port it
/// bound (it binds port 0 and says which it got).
type Peer = (Child, BufReader<std::process::ChildStdout>, u16);

/// Starts the pymavlink vehicle; returns once its socket is bound.
fn start_peer(key: Option<&str>, seconds: f64, serve_upload: bool) -> anyhow::Result<Peer> {
    start_peer_as(key, seconds, serve_upload, "px4")
}

/// [`start_peer`] with the autopilot it claims to be (`px4`, `ardupilot`).
fn start_peer_as(
    key: Option<&str>,
    seconds: f64,
    serve_upload: bool,
    autopilot: &str,
) -> anyhow::Result<Peer> {
    let script = crate::repo_root().join("tests/peers/pymavlink_vehicle.py");
    let mut cmd = Command::new(crate::link_support::python());
    cmd.arg(script)
        .arg("--port")
        .arg("0")
        .arg("--seconds")
        .arg(seconds.to_string());
    if let Some(k) = key {
        cmd.arg("--key").arg(k);
    }
    if serve_upload {
        cmd.arg("--serve-upload");
    }
    cmd.arg("--autopilot").arg(autopilot);
    let mut child = cmd.stdout(Stdio::piped()).spawn()?;
    let stdout = child
        .stdout
        .take()
        .ok_or_else(|| anyhow::anyhow!("no stdout"))?;
    let mut reader = BufReader::new(stdout);
    let mut line = String::new();
    reader.read_line(&mut line)?;
    let port = line
        .trim()
        .strip_prefix("ready ")
        .and_then(|p| p.parse::<u16>().ok())
        .ok_or_else(|| anyhow::anyhow!("peer said {line:?}"))?;
    Ok((child, reader, port))
}

fn finish_peer(
    mut child: Child,
    mut reader: BufReader<std::process::ChildStdout>,
) -> anyhow::Result<serde_json::Value> {
    let mut line = String::new();
    reader.read_line(&mut line)?;
    child.wait()?;
    Ok(serde_json::from_str(&line)?)
}

fn link_params(port: u16, key: Option<&str>) -> Params {
    Params {
        url: format!("udpout:127.0.0.1:{port}"),
        signing: key.map(|k| Signing {
            key_hex: k.into(),
            link_id: 3,
            allow_unsigned: false,
        }),
        ..Params::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs pymavlink"]
async fn pymavlink_decodes_heartbeat_and_items() -> anyhow::Result<()> {
    let (child, reader, port) = start_peer(None, 10.0, true)?;
    let cancel = CancellationToken::new();
    let (link, _task) = vehicle::spawn(
        link_params(port, None),
        upload::Params::default(),
        cancel.clone(),
    )?;
    let v = link.wait_for_vehicle(Duration::from_secs(6)).await?;
    assert_eq!(v.flavour, Some(Flavour::Px4));
    let home = Home {
        lat_deg: 47.397742,
        lon_deg: 8.545594,
        alt_amsl_m: 488.0,
    };
    let target = Target {
        lat_deg: 47.3981,
        lon_deg: 8.5452,
        alt_m: 22.5,
        yaw_deg: 135.0,
        gimbal_pitch_deg: -40.0,
        photo: true,
    };
    let items = plan::plan(&target, &home, Flavour::Px4, &plan::Params::default())?;
    link.upload_mission(items.clone()).await?;
    let out = tokio::task::spawn_blocking(move || finish_peer(child, reader)).await??;
    cancel.cancel();

    let hb = &out["first_heartbeat"];
    assert_eq!(hb["sysid"], 255);
    assert_eq!(hb["compid"], 191);
    assert_eq!(hb["type"], 6, "MAV_TYPE_GCS");
    assert_eq!(hb["autopilot"], 8, "MAV_AUTOPILOT_INVALID");
    assert_eq!(hb["system_status"], 4, "MAV_STATE_ACTIVE");
    assert_eq!(hb["mavlink_version"], 3);
    let got = out["items"]
        .as_array()
        .ok_or_else(|| anyhow::anyhow!("no items: {out}"))?;
    assert_eq!(got.len(), items.len());
    for (g, i) in got.iter().zip(&items) {
        assert_eq!(g["seq"], i.seq);
        assert_eq!(g["command"], i.command);
        assert_eq!(g["frame"], i.frame);
        assert_eq!(g["x"], i.x);
        assert_eq!(g["y"], i.y);
        assert_eq!(g["target_system"], 1);
        assert_eq!(g["target_component"], 1);
        assert_eq!(g["mission_type"], 0);
        assert_eq!(g["autocontinue"], 1);
        for k in 0..4 {
            let p = i.params[k];
            if p.is_nan() {
                assert!(g["params"][k].is_null());
            } else {
                assert_eq!(
                    g["params"][k].as_f64(),
                    Some(f64::from(p)),
                    "item {} param{}",
                    i.seq,
                    k + 1
                );
            }
        }
    }
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs pymavlink"]
async fn signed_frames_verify_with_the_right_key() -> anyhow::Result<()> {
    let (child, reader, port) = start_peer(Some(KEY), 4.0, false)?;
    let cancel = CancellationToken::new();
    let (link, _task) = vehicle::spawn(
        link_params(port, Some(KEY)),
        upload::Params::default(),
        cancel.clone(),
    )?;
    // pymavlink signs its heartbeats with the same key: we accept them
    let v = link.wait_for_vehicle(Duration::from_secs(4)).await?;
    assert_eq!(v.system_id, Some(1));
    let out = tokio::task::spawn_blocking(move || finish_peer(child, reader)).await??;
    cancel.cancel();
    let n = out["heartbeats"].as_u64().unwrap_or(0);
    assert!(n >= 2, "{out}");
    assert_eq!(
        out["signed_heartbeats"].as_u64(),
        Some(n),
        "every heartbeat signed and verified: {out}"
    );
    assert_eq!(out["badsig"], 0);
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs pymavlink"]
async fn signed_frames_are_rejected_with_a_wrong_key() -> anyhow::Result<()> {
    let (child, reader, port) = start_peer(Some(WRONG), 4.0, false)?;
    let cancel = CancellationToken::new();
    let (link, _task) = vehicle::spawn(
        link_params(port, Some(KEY)),
        upload::Params::default(),
        cancel.clone(),
    )?;
    // the vehicle's frames carry the wrong key: we never accept it
    let r = link.wait_for_vehicle(Duration::from_secs(3)).await;
    assert!(matches!(r, Err(LinkError::Timeout { .. })), "{r:?}");
    let out = tokio::task::spawn_blocking(move || finish_peer(child, reader)).await??;
    cancel.cancel();
    assert_eq!(
        out["heartbeats"], 0,
        "pymavlink accepted none of ours: {out}"
    );
    assert!(
        out["badsig"].as_u64().unwrap_or(0) >= 2,
        "and counted them as bad signatures: {out}"
    );
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs pymavlink"]
async fn unsigned_frames_are_rejected_by_a_signing_peer() -> anyhow::Result<()> {
    // control: without a key on our side, our frames are unsigned, and a
    // pymavlink vehicle that insists on signatures rejects them
    let (child, reader, port) = start_peer(Some(KEY), 3.0, false)?;
    let cancel = CancellationToken::new();
    let (_link, _task) = vehicle::spawn(
        link_params(port, None),
        upload::Params::default(),
        cancel.clone(),
    )?;
    let out = tokio::task::spawn_blocking(move || finish_peer(child, reader)).await??;
    cancel.cancel();
    assert_eq!(out["heartbeats"], 0, "{out}");
    Ok(())
}

/// `shotpilot mission upload` to a pymavlink vehicle claiming `autopilot`:
/// the items pymavlink decoded, and the same target's `mission plan --json`.
fn upload_via_cli(
    autopilot: &str,
) -> anyhow::Result<(Vec<serde_json::Value>, Vec<serde_json::Value>)> {
    let (child, reader, port) = start_peer_as(None, 15.0, true, autopilot)?;
    let target = "47.3981,8.5452,22.5,135,-40";
    let home = "47.397742,8.545594,488";
    let up = Command::new(env!("CARGO_BIN_EXE_shotpilot"))
        .args(["--log", "warn", "mission", "upload", "--link"])
        .arg(format!("udpout:127.0.0.1:{port}"))
        .args(["--target", target, "--home", home, "--no-verify", "--json"])
        .output()?;
    anyhow::ensure!(
        up.status.success(),
        "upload: {}",
        String::from_utf8_lossy(&up.stderr)
    );
    let out = finish_peer(child, reader)?;
    let decoded = out["items"]
        .as_array()
        .cloned()
        .ok_or_else(|| anyhow::anyhow!("the peer decoded no mission: {out}"))?;
    let dir = tempfile::tempdir()?;
    let planned = Command::new(env!("CARGO_BIN_EXE_shotpilot"))
        .args([
            "--log",
            "warn",
            "mission",
            "plan",
            "--json",
            "--flavour",
            autopilot,
        ])
        .args(["--target", target, "--home", home, "--qgc-plan"])
        .arg(dir.path().join("p.plan"))
        .output()?;
    anyhow::ensure!(planned.status.success());
    let j: serde_json::Value = serde_json::from_slice(&planned.stdout)?;
    let planned = j["items"].as_array().cloned().unwrap_or_default();
    Ok((decoded, planned))
}

#[test]
#[ignore = "needs pymavlink"]
fn pymavlink_decodes_gimbal_manager_items_on_both_flavours() -> anyhow::Result<()> {
    for autopilot in ["px4", "ardupilot"] {
        let (decoded, planned) = upload_via_cli(autopilot)?;
        assert_eq!(decoded.len(), planned.len(), "{autopilot}: {decoded:?}");
        for (d, p) in decoded.iter().zip(&planned) {
            assert_eq!(d["command"], p["command"], "{autopilot}");
        }
        let names: Vec<&str> = decoded
            .iter()
            .map(|d| d["command_name"].as_str().unwrap_or("?"))
            .collect();
        let pitchyaw = decoded
            .iter()
            .find(|d| d["command_name"] == "MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW")
            .ok_or_else(|| anyhow::anyhow!("{autopilot}: no PITCHYAW in {names:?}"))?;
        assert_eq!(
            pitchyaw["params"][0].as_f64(),
            Some(-40.0),
            "{autopilot}: pitch"
        );
        assert_eq!(
            pitchyaw["params"][1].as_f64(),
            Some(0.0),
            "{autopilot}: yaw"
        );
        assert_eq!(pitchyaw["x"], 4 | 8 | 32, "{autopilot}: flags");
        assert!(
            !names.contains(&"MAV_CMD_DO_MOUNT_CONTROL"),
            "{autopilot}: {names:?}"
        );
        let configures: Vec<&serde_json::Value> = decoded
            .iter()
            .filter(|d| d["command_name"] == "MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE")
            .collect();
        if autopilot == "px4" {
            // take control (-2: the autopilot itself) before the PITCHYAW, release (-3) last
            assert_eq!(configures.len(), 2, "{names:?}");
            assert!(configures[0]["seq"].as_u64() < pitchyaw["seq"].as_u64());
            assert_eq!(configures[0]["params"][0].as_f64(), Some(-2.0));
            assert_eq!(configures[1]["params"][0].as_f64(), Some(-3.0));
            assert_eq!(
                configures[1]["seq"].as_u64(),
                Some(decoded.len() as u64 - 1)
            );
        } else {
            assert!(
                configures.is_empty(),
                "ArduPilot has no configure mission item: {names:?}"
            );
        }
        println!("{autopilot}: pymavlink decoded {names:?}");
    }
    Ok(())
}
