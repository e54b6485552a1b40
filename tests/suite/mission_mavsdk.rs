//! MAVSDK (PyPI `mavsdk`: the C++ library, in-process via its C bindings)
//! acting as an autopilot with `MissionRawServer` receives exactly the items
//! shotpilot plans, for both flavours' item sets.
//!
//! Needs `mavsdk` in the Python at `$SHOTPILOT_PYTHON` (default
//! `/work/venv/bin/python`).

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::Duration;

use shotpilot::mission::plan::{self, Flavour, Home, Target};
use shotpilot::mission::upload;
use shotpilot::vehicle::{self, Params};
use tokio_util::sync::CancellationToken;

async fn mavsdk_receives(flavour: Flavour) -> anyhow::Result<()> {
    // Our link listens on a port the kernel picks; MAVSDK sends there (it
    // cannot report a port it bound itself).
    let cancel = CancellationToken::new();
    let p = Params {
        url: "udpin:127.0.0.1:0".into(),
        ..Params::default()
    };
    let (link, _task) = vehicle::spawn(p, upload::Params::default(), cancel.clone())?;
    let port = link.bound_addr(Duration::from_secs(5)).await?.port();
    let script = crate::repo_root().join("tests/peers/mavsdk_autopilot.py");
    let mut child = Command::new(crate::link_support::python())
        .arg(script)
        .arg("--gcs-port")
        .arg(port.to_string())
        .stdout(Stdio::piped())
        .spawn()?;
    let stdout = child
        .stdout
        .take()
        .ok_or_else(|| anyhow::anyhow!("no stdout"))?;
    let mut reader = BufReader::new(stdout);
    let mut line = String::new();
    reader.read_line(&mut line)?;
    anyhow::ensure!(line.trim() == "ready", "peer said {line:?}");

    let v = link.wait_for_vehicle(Duration::from_secs(8)).await?;
    let home = Home {
        lat_deg: -35.363261,
        lon_deg: 149.165230,
        alt_amsl_m: 584.0,
    };
    let target = Target {
        lat_deg: -35.36290,
        lon_deg: 149.16550,
        alt_m: 30.0,
        yaw_deg: 200.0,
        gimbal_pitch_deg: -25.0,
        photo: true,
    };
    let items = plan::plan(&target, &home, flavour, &plan::Params::default())?;
    let report = link.upload_mission(items.clone()).await?;
    line.clear();
    let out: serde_json::Value =
        tokio::task::spawn_blocking(move || -> anyhow::Result<serde_json::Value> {
            reader.read_line(&mut line)?;
            child.wait()?;
            Ok(serde_json::from_str(&line)?)
        })
        .await??;
    cancel.cancel();
    println!(
        "MAVSDK autopilot (sys {:?}, comp {}): {:?} plan of {} items uploaded in {:.3} s, {} retries",
        v.system_id, v.component_id, flavour, report.items, report.seconds, report.retries
    );
    let got = out["items"]
        .as_array()
        .ok_or_else(|| anyhow::anyhow!("MAVSDK got no mission: {out}"))?;
    assert_eq!(got.len(), items.len(), "{out}");
    for (g, i) in got.iter().zip(&items) {
        assert_eq!(g["seq"], i.seq);
        assert_eq!(g["command"], i.command);
        assert_eq!(g["frame"], i.frame);
        assert_eq!(g["x"], i.x);
        assert_eq!(g["y"], i.y);
        assert_eq!(g["autocontinue"], u8::from(i.autocontinue));
        assert_eq!(g["mission_type"], 0);
        for k in 0..4 {
            let p = i.params[k];
            if p.is_nan() {
                assert!(g["params"][k].is_null(), "item {} param{}", i.seq, k + 1);
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
        if i.z.is_nan() {
            assert!(g["z"].is_null());
        } else {
            assert_eq!(g["z"].as_f64(), Some(f64::from(i.z)));
        }
    }
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs mavsdk"]
async fn mavsdk_mission_raw_server_receives_px4_plan() -> anyhow::Result<()> {
    mavsdk_receives(Flavour::Px4).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs mavsdk"]
async fn mavsdk_mission_raw_server_receives_ardupilot_plan() -> anyhow::Result<()> {
    mavsdk_receives(Flavour::ArduPilot).await
}
