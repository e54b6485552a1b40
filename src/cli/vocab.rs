//! `shotpilot vocab ...`: train a bag-of-words vocabulary from images, import
//! a DBoW2 text vocabulary, describe a vocabulary file.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;

use shotpilot::bow::{TrainParams, TrainPhase, Vocabulary};
use shotpilot::features::{self, OrbExtractor};
use shotpilot::video::dataset::{Dataset, DatasetError, load_gray};

/// `shotpilot vocab` arguments.
#[derive(Args, Debug)]
pub struct VocabArgs {
    #[command(subcommand)]
    command: VocabCommand,
}

#[derive(Subcommand, Debug)]
enum VocabCommand {
    /// Train a vocabulary on the ORB descriptors of images.
    ///
    /// Each INPUT is a dataset folder (TUM or EuRoC layout, as `eval` reads),
    /// a folder of PNG/JPEG images (sorted by name) or one image file. The
    /// vocabulary is written in shotpilot's binary format.
    Train(TrainArgs),
    /// Convert a DBoW2 text vocabulary (ORB-SLAM's ORBvoc.txt) to the binary
    /// format.
    Import(ImportArgs),
    /// Describe a vocabulary file and time loading it.
    Info(InfoArgs),
}

#[derive(Args, Debug)]
struct TrainArgs {
    /// Datasets, image folders or image files.
    #[arg(required = true, value_name = "INPUT")]
    inputs: Vec<PathBuf>,
    /// Output vocabulary file.
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    /// Branching factor.
    #[arg(long, default_value_t = 10)]
    k: u32,
    /// Depth of the tree (levels below the root).
    #[arg(long, default_value_t = 6)]
    levels: u32,
    /// Seed of the clustering.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// ORB features extracted per image.
    #[arg(long, default_value_t = 1000, value_name = "N")]
    features: usize,
    /// Use every N-th image of each input.
    #[arg(long, default_value_t = 1, value_name = "N")]
    every: usize,
    /// Most k-majority rounds per node.
    #[arg(long, default_value_t = 25, value_name = "N")]
    max_iterations: u32,
    /// Print exactly one JSON object on stdout instead of text.
    #[arg(long)]
    json: bool,
}

#[derive(Args, Debug)]
struct ImportArgs {
    /// DBoW2 text vocabulary (`k L scoring weighting`, then one line per node).
    #[arg(value_name = "ORBVOC_TXT")]
    input: PathBuf,
    /// Output vocabulary file.
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    /// Print exactly one JSON object on stdout instead of text.
    #[arg(long)]
    json: bool,
}

#[derive(Args, Debug)]
struct InfoArgs {
    /// Vocabulary file (binary format).
    #[arg(value_name = "FILE")]
    file: PathBuf,
    /// Print exactly one JSON object on stdout instead of text.
    #[arg(long)]
    json: bool,
}

/// Run a `vocab` subcommand.
pub fn run(args: VocabArgs) -> Result<()> {
    match args.command {
        VocabCommand::Train(a) => train(a),
        VocabCommand::Import(a) => import(a),
        VocabCommand::Info(a) => info(a),
    }
}

fn is_image(p: &Path) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase())
        .is_some_and(|e| matches!(e.as_str(), "png" | "jpg" | "jpeg"))
}

/// The image files an input stands for, every `every`-th.
fn input_images(input: &Path, every: usize) -> Result<Vec<PathBuf>> {
    if input.is_file() {
        return Ok(vec![input.to_path_buf()]);
    }
    if !input.is_dir() {
        bail!("{}: no such file or folder", input.display());
    }
    match Dataset::open(input) {
        Ok(ds) => Ok((0..ds.len())
            .step_by(every)
            .filter_map(|i| ds.image_path(i).map(Path::to_path_buf))
            .collect()),
        Err(DatasetError::UnknownLayout { .. }) => {
            let mut files: Vec<PathBuf> = std::fs::read_dir(input)
                .with_context(|| format!("listing {}", input.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.is_file() && is_image(p))
                .collect();
            files.sort();
            if files.is_empty() {
                bail!(
                    "{}: neither a dataset nor a folder of PNG/JPEG images",
                    input.display()
                );
            }
            Ok(files.into_iter().step_by(every).collect())
        }
        Err(e) => Err(e).with_context(|| format!("opening dataset {}", input.display())),
    }
}

fn bar(len: u64, what: &str) -> ProgressBar {
    let pb = ProgressBar::new(len);
    pb.set_style(
        ProgressStyle::with_template(
            "{msg:>10} [{elapsed_precise}] {wide_bar} {pos}/{len} (eta {eta})",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    pb.set_message(what.to_string());
    pb
}

fn train(a: TrainArgs) -> Result<()> {
    if a.every == 0 {
        bail!("--every must be at least 1");
    }
    let mut files = Vec::new();
    for input in &a.inputs {
        files.extend(input_images(input, a.every)?);
    }
    tracing::info!(images = files.len(), "extracting ORB features");
    let mut extractor = OrbExtractor::new(features::Params {
        n_features: a.features,
        ..features::Params::default()
    })?;
    let t0 = Instant::now();
    let pb = bar(files.len() as u64, "extracting");
    let mut images: Vec<Vec<[u64; 4]>> = Vec::with_capacity(files.len());
    let mut featureless = 0usize;
    for f in &files {
        let img = load_gray(f)?;
        let feats = extractor.extract(&img, None);
        if feats.descriptors.is_empty() {
            featureless += 1;
        } else {
            images.push(feats.descriptors);
        }
        pb.inc(1);
    }
    pb.finish_and_clear();
    let extract_s = t0.elapsed().as_secs_f64();
    let descriptors: usize = images.iter().map(Vec::len).sum();
    if featureless > 0 {
        tracing::warn!(featureless, "images without features were left out");
    }
    tracing::info!(
        images = images.len(),
        descriptors,
        seconds = extract_s,
        "features extracted"
    );

    let params = TrainParams {
        k: a.k,
        levels: a.levels,
        seed: a.seed,
        max_iterations: a.max_iterations,
    };
    let t1 = Instant::now();
    let mut pb = bar(1, TrainPhase::Clustering.name());
    let mut phase = TrainPhase::Clustering;
    let voc = Vocabulary::train(&images, &params, &mut |p| {
        if p.phase != phase {
            pb.finish_and_clear();
            pb = bar(p.total, p.phase.name());
            phase = p.phase;
        }
        pb.set_length(p.total);
        pb.set_position(p.done);
    })?;
    pb.finish_and_clear();
    let train_s = t1.elapsed().as_secs_f64();

    voc.save(&a.out)?;
    let file_bytes = std::fs::metadata(&a.out)
        .with_context(|| format!("reading back {}", a.out.display()))?
        .len();
    let t2 = Instant::now();
    let back = Vocabulary::load(&a.out)?;
    let load_ms = t2.elapsed().as_secs_f64() * 1e3;
    if back != voc {
        bail!("{} does not read back as written", a.out.display());
    }
    let zero_weight = (0..voc.word_count() as u32)
        .filter(|&w| voc.word_weight(shotpilot::bow::WordId(w)) == Some(0.0))
        .count();
    if a.json {
        println!(
            "{}",
            json!({
                "out": a.out,
                "images": images.len(),
                "images_without_features": featureless,
                "descriptors": descriptors,
                "k": voc.branching(),
                "levels": voc.levels(),
                "seed": a.seed,
                "nodes": voc.node_count(),
                "words": voc.word_count(),
                "zero_weight_words": zero_weight,
                "file_bytes": file_bytes,
                "extract_s": extract_s,
                "train_s": train_s,
                "load_ms": load_ms,
            })
        );
    } else {
        println!(
            "trained k={} L={} on {} images ({} descriptors): {} nodes, {} words ({} with weight 0)",
            voc.branching(),
            voc.levels(),
            images.len(),
            descriptors,
            voc.node_count(),
            voc.word_count(),
            zero_weight
        );
        println!(
            "extraction {extract_s:.2} s, training {train_s:.2} s; wrote {} ({file_bytes} bytes, loads in {load_ms:.2} ms)",
            a.out.display()
        );
    }
    Ok(())
}

fn import(a: ImportArgs) -> Result<()> {
    let t0 = Instant::now();
    let voc = Vocabulary::import_dbow2_text(&a.input)?;
    let import_s = t0.elapsed().as_secs_f64();
    voc.save(&a.out)?;
    let file_bytes = std::fs::metadata(&a.out)
        .with_context(|| format!("reading back {}", a.out.display()))?
        .len();
    let t1 = Instant::now();
    let back = Vocabulary::load(&a.out)?;
    let load_ms = t1.elapsed().as_secs_f64() * 1e3;
    if back != voc {
        bail!("{} does not read back as written", a.out.display());
    }
    if a.json {
        println!(
            "{}",
            json!({
                "input": a.input,
                "out": a.out,
                "k": voc.branching(),
                "levels": voc.levels(),
                "nodes": voc.node_count(),
                "words": voc.word_count(),
                "import_s": import_s,
                "file_bytes": file_bytes,
                "load_ms": load_ms,
            })
        );
    } else {
        println!(
            "imported {} in {import_s:.2} s: k={} L={}, {} nodes, {} words",
            a.input.display(),
            voc.branching(),
            voc.levels(),
            voc.node_count(),
            voc.word_count()
        );
        println!(
            "wrote {} ({file_bytes} bytes, loads in {load_ms:.2} ms)",
            a.out.display()
        );
    }
    Ok(())
}

fn info(a: InfoArgs) -> Result<()> {
    let t0 = Instant::now();
    let voc = Vocabulary::load(&a.file)?;
    let load_ms = t0.elapsed().as_secs_f64() * 1e3;
    let file_bytes = std::fs::metadata(&a.file)
        .with_context(|| format!("reading {}", a.file.display()))?
        .len();
    if a.json {
        println!(
            "{}",
            json!({
                "file": a.file,
                "k": voc.branching(),
                "levels": voc.levels(),
                "weighting": format!("{:?}", voc.weighting()),
                "scoring": format!("{:?}", voc.scoring()),
                "nodes": voc.node_count(),
                "words": voc.word_count(),
                "file_bytes": file_bytes,
                "load_ms": load_ms,
            })
        );
    } else {
        println!(
            "{}: k={} L={} {:?}/{:?}, {} nodes, {} words, {file_bytes} bytes, loaded in {load_ms:.2} ms",
            a.file.display(),
            voc.branching(),
            voc.levels(),
            voc.weighting(),
            voc.scoring(),
            voc.node_count(),
            voc.word_count()
        );
    }
    Ok(())
}
