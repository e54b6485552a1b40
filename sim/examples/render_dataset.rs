//! Renders a TUM-layout dataset until the `shotpilot-sim render` subcommand
//! exists: `cargo run --release -p shotpilot-sim --example render_dataset --
//! --path explore|orbit|FILE --frames N --out DIR [--seed S] [--noise SIGMA]`.

use std::path::PathBuf;

use anyhow::{Context, bail};
use shotpilot_sim::camera::SimCamera;
use shotpilot_sim::dataset::render_dataset;
use shotpilot_sim::paths::PathSpec;

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .init();
    let mut path = PathSpec::Explore;
    let mut frames = 600usize;
    let mut out = PathBuf::from("/tmp/sim_dataset");
    let mut seed = 1u64;
    let mut noise = 2.0f32;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut val = || args.next().with_context(|| format!("{a} needs a value"));
        match a.as_str() {
            "--path" => path = val()?.parse()?,
            "--frames" => frames = val()?.parse()?,
            "--out" => out = val()?.into(),
            "--seed" => seed = val()?.parse()?,
            "--noise" => noise = val()?.parse()?,
            other => bail!("unknown argument {other}"),
        }
    }
    let report = render_dataset(path, frames, &out, seed, SimCamera::default(), noise)?;
    println!(
        "{} frames to {}: world {:.2} s, render {:.2} s wall ({:.1} frames/s), {} cpu, write {:.2} s",
        report.frames,
        report.out_dir.display(),
        report.world_seconds,
        report.render_seconds,
        report.render_fps(),
        report
            .render_fps_cpu()
            .map_or("n/a".to_string(), |f| format!(
                "{:.2} s ({f:.1} frames/s)",
                report.render_cpu_seconds.unwrap_or(0.0)
            )),
        report.write_seconds
    );
    Ok(())
}
