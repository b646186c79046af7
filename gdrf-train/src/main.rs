//! gdrf-train: train GDRF generators (`--config`, `--resume`), plot a run's losses, and
//! prepare datasets (generate the procedural dataset, render swaps, inspect and cache
//! image folders).
mod eval_cmd;
mod plot_cmd;
mod train_cmd;

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand};
use gdrf_core::config::CameraPreset;
use gdrf_core::data::layouts::Layout;
use gdrf_core::data::synth::{self, Category, SynthOptions};
use gdrf_core::data::{self, CacheStatus, DataConfig, LoadOptions, Metadata, Prepared};
use gdrf_core::progress;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Train GDRF generators and prepare their training images.
///
/// Training: `gdrf-train --config configs/chairs-tiny.toml` starts a run in
/// runs/<config name>/ (checkpoints, metrics.jsonl, sample/swap/template grids, the EMA
/// generator); Ctrl-C or SIGTERM writes a checkpoint and stops; `--resume RUN_DIR`
/// continues exactly where it stopped. `gdrf-train plot RUN_DIR` draws the loss curves.
/// The `dataset` commands generate the built-in procedural dataset, render
/// shape/appearance swaps from it, and load image collections into the training cache
/// (see docs/datasets.md).
#[derive(Parser)]
#[command(version, about, long_about)]
struct Cli {
    #[command(flatten)]
    train: train_cmd::TrainArgs,
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand)]
enum Command {
    /// Procedural datasets and image collections.
    #[command(subcommand)]
    Dataset(DatasetCommand),
    /// Draw a run's loss curves, gradient norms, learning rates and speed to a PNG.
    Plot(plot_cmd::PlotArgs),
    /// Score a generator (Fréchet/kernel distances, topology coverage, disentanglement,
    /// pose consistency beside real-data and random-generator ends), or train the probe
    /// those scores need (`eval train-probe`).
    Eval(Box<eval_cmd::EvalArgs>),
    /// Blend two generators of one architecture in weight space: every parameter becomes
    /// (1 − t)·FROM + t·TO. Meant for a run trained on from another (FROM its start, TO
    /// its end), where points between can keep what each end does better; score them with
    /// `gdrf-train eval`. Training checkpoints give their EMA generator.
    Interpolate(InterpolateArgs),
    /// Copy the generator a run's learning curve ranks best into a model folder: the
    /// evaluations that meet the goal on every seed come first (every calibrated position at
    /// least 0.75, yaw error at most 40°, structure at least 0.75, colour at least its real
    /// end); among them, or among all while none does, the one whose lowest seed-mean
    /// position over the calibrated scores (Fréchet and kernel distance, coverage,
    /// structure, yaw, pitch) is highest, ties to the later step (docs/training.md, "The
    /// campaign"). Writes DIR/generator.safetensors and DIR/seeds.json, that evaluation's
    /// scores; where its evaluation folder lost them, from the run's checkpoint of that step
    /// and the curve. A generator DIR already holds is replaced only when that evaluation
    /// ranks above it by the same rule, scored the same way: its DIR/seeds.json, or
    /// DIR/seeds-R.json where it was shipped at another resolution than the curve's R.
    Ship(ShipArgs),
    /// Copy a run's full training state into one folder that `--resume` continues from: its
    /// newest checkpoint (both networks, the EMA, both optimisers, the counters), config.toml,
    /// metrics.jsonl, its learning curve (curve.jsonl, curve.png, filmstrip.png) and each
    /// evaluation's filmstrip row (evals/step-N/frame.png), so that the resumed run draws the
    /// whole filmstrip again. DIR is replaced whole (made beside it, then renamed into place);
    /// the run must not be training (its lock is taken). The campaign commits this copy
    /// (`scripts/campaign.sh snapshot`).
    Snapshot(SnapshotArgs),
}

#[derive(Args)]
struct SnapshotArgs {
    /// A run directory written by `gdrf-train --config`.
    run_dir: PathBuf,
    /// The folder to write: missing, empty, or an earlier snapshot or run directory (one
    /// that holds config.toml or checkpoints/), which is replaced.
    #[arg(long)]
    out: PathBuf,
}

#[derive(Args)]
struct ShipArgs {
    /// A run directory whose config has `[eval] interval` (its curve.jsonl and evals/).
    run_dir: PathBuf,
    /// The model folder (created when missing; its generator.safetensors and seeds.json are
    /// replaced atomically).
    #[arg(long)]
    out: PathBuf,
}

#[derive(Args)]
struct InterpolateArgs {
    /// The generator at t = 0 (an exported generator or a training checkpoint).
    #[arg(long)]
    from: PathBuf,
    /// The generator at t = 1; same generator config and camera as --from.
    #[arg(long)]
    to: PathBuf,
    /// Weight of --to, in [0, 1].
    #[arg(long)]
    t: f64,
    /// Another weight for the parameters under a name prefix, e.g.
    /// `--t-for template.trunk=0.25` (repeatable; the longest matching prefix wins). The
    /// generator's groups: shape_mapping, deform (the shape side), template.trunk and
    /// template.sigma_head (the template's geometry), template.color, template.rgb_head
    /// and appearance_mapping (its appearance).
    #[arg(long = "t-for", value_name = "PREFIX=T", value_parser = parse_group_weight)]
    t_for: Vec<(String, f64)>,
    /// Output generator (.safetensors), written atomically.
    #[arg(long)]
    out: PathBuf,
}

#[derive(Subcommand)]
enum DatasetCommand {
    /// Render a procedural dataset: images/*.png, metadata.json (pose, shape and
    /// appearance parameters, seed, split per image) and camera_param.json.
    Synth(SynthArgs),
    /// Render "the shape of object I with the appearance of object J" from a generated dataset.
    Swap(SwapArgs),
    /// Load a dataset folder (any layout) at a training resolution, fill its cache, and
    /// report the image count, poses and images/second.
    Inspect(InspectArgs),
    /// Generate (if needed) and load the dataset named by a training config's [data] table.
    Prepare(PrepareArgs),
}

#[derive(Args)]
struct SynthArgs {
    /// Object category: chairs or tables.
    #[arg(long, default_value = "chairs")]
    category: Category,
    /// Number of images.
    #[arg(long)]
    count: usize,
    /// Image side in pixels (64 and 128 are the training resolutions).
    #[arg(long)]
    resolution: usize,
    /// Output folder (created; must not already hold a dataset unless --force).
    #[arg(long)]
    out: PathBuf,
    /// Dataset seed: the same seed and options give byte-identical images.
    #[arg(long, default_value_t = SynthOptions::default().seed)]
    seed: u64,
    /// Antialiasing: K × K samples per pixel.
    #[arg(long, default_value_t = SynthOptions::default().supersample)]
    supersample: usize,
    /// Views rendered of each object.
    #[arg(long, default_value_t = SynthOptions::default().views_per_object)]
    views_per_object: usize,
    /// Fraction of objects held out of training (all their views).
    #[arg(long, default_value_t = SynthOptions::default().held_out_fraction)]
    held_out: f64,
    /// Turn off soft shadows (faster).
    #[arg(long)]
    no_shadows: bool,
    /// Camera preset for field of view, ray range and pose distribution.
    #[arg(long, value_enum, default_value = "chair")]
    camera: CameraPreset,
    /// Worker threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Also write contact-sheet.png: 64 random images in an 8 × 8 grid.
    #[arg(long)]
    contact_sheet: bool,
    /// Replace a dataset already in --out.
    #[arg(long)]
    force: bool,
}

#[derive(Args)]
struct SwapArgs {
    /// A folder written by `gdrf-train dataset synth`.
    #[arg(long)]
    dataset: PathBuf,
    /// Object whose shape is rendered.
    #[arg(long)]
    shape_from: usize,
    /// Object whose materials are used.
    #[arg(long)]
    appearance_from: usize,
    /// Camera pitch φ in radians (polar angle from +y); default: the shape object's pose.
    #[arg(long, requires = "yaw", allow_negative_numbers = true)]
    pitch: Option<f64>,
    /// Camera yaw θ in radians.
    #[arg(long, requires = "pitch", allow_negative_numbers = true)]
    yaw: Option<f64>,
    /// Image side (default: the dataset's).
    #[arg(long)]
    resolution: Option<usize>,
    /// Samples per pixel per axis (default: the dataset's).
    #[arg(long)]
    supersample: Option<usize>,
    /// Output PNG (RGBA).
    #[arg(long)]
    out: PathBuf,
}

#[derive(Args)]
struct InspectArgs {
    /// Dataset folder.
    dir: PathBuf,
    /// auto, folder, camera_param, carla or synth.
    #[arg(long, default_value = "auto")]
    layout: Layout,
    /// Pose file (folder layout: camera_param-format JSON) or CARLA pose folder.
    #[arg(long)]
    poses: Option<PathBuf>,
    /// Training resolution to decode and cache at.
    #[arg(long, default_value_t = 64)]
    resolution: usize,
    /// Fail if the dataset has no poses.
    #[arg(long)]
    require_poses: bool,
    /// Skip bad files with a warning instead of stopping at the first.
    #[arg(long)]
    skip_bad: bool,
    /// Synthetic datasets: train, held_out or all.
    #[arg(long, default_value = "all", value_parser = ["train", "held_out", "all"])]
    split: String,
    /// Neither read nor write the cache.
    #[arg(long)]
    no_cache: bool,
    /// Decoding threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Write a contact sheet of 64 random images to this PNG.
    #[arg(long)]
    contact_sheet: Option<PathBuf>,
}

#[derive(Args)]
struct PrepareArgs {
    /// Training config with a [data] table (other tables are ignored here).
    #[arg(long)]
    config: PathBuf,
    /// Training resolution to load at.
    #[arg(long, default_value_t = 64)]
    resolution: usize,
    #[arg(long, default_value_t = 0)]
    threads: usize,
}

fn main() {
    let cli = Cli::parse();
    progress::set_quiet(cli.train.quiet);
    let usage = |message: &str| {
        eprintln!("error: {message}");
        std::process::exit(2);
    };
    let result = match cli.command {
        Some(_) if cli.train.any() => usage(
            "--config, --resume and --print-config start or inspect training; they cannot be combined with a subcommand",
        ),
        Some(Command::Dataset(cmd)) => dataset(cmd),
        Some(Command::Plot(a)) => plot_cmd::plot(a),
        Some(Command::Eval(a)) => eval_cmd::eval(*a),
        Some(Command::Interpolate(a)) => interpolate_cmd(a),
        Some(Command::Ship(a)) => ship_cmd(a),
        Some(Command::Snapshot(a)) => snapshot_cmd(a),
        None if cli.train.any() => train_cmd::train(cli.train),
        None => usage("nothing to do: pass --config FILE, --resume RUN_DIR or a subcommand; see `gdrf-train --help`"),
    };
    // Usage errors exit 2 (clap's, and the two above); everything found later exits 1, as
    // in gdrf-edit and gdrf-invert.
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn parse_group_weight(s: &str) -> std::result::Result<(String, f64), String> {
    let (prefix, t) =
        s.split_once('=').ok_or_else(|| format!("expected PREFIX=T (e.g. template.trunk=0.25), got {s:?}"))?;
    let t = t.parse::<f64>().map_err(|_| format!("expected a number after '=', got {t:?}"))?;
    if prefix.is_empty() {
        return Err("expected a parameter-name prefix before '='".into());
    }
    Ok((prefix.to_string(), t))
}

fn ship_cmd(a: ShipArgs) -> Result<()> {
    let shipped = gdrf_core::train::curve::ship(&a.run_dir, &a.out)?;
    let p = &shipped.point;
    let whither = if let Some(k) = &shipped.kept {
        format!(
            ": {} keeps its own generator, unchanged: it {} the goal, lowest position {:.3} ({}), at or above this step's",
            a.out.display(),
            if k.meets_goal { "meets" } else { "is short of" },
            k.lowest,
            k.score
        )
    } else if shipped.unchanged {
        format!(": already in {}, unchanged (its seeds.json holds this step's scores)", a.out.display())
    } else {
        format!(" -> {} (from {})", a.out.join("generator.safetensors").display(), shipped.from.display())
    };
    println!(
        "step {} of {} evaluations: {} the goal on every seed, lowest position {:.3} ({}){whither}",
        p.step,
        shipped.evaluations,
        if p.meets_goal { "meets" } else { "short of" },
        p.lowest,
        p.score,
    );
    let (curve, metrics) =
        (gdrf_core::train::curve::read(&a.run_dir)?, gdrf_core::train::run::read_metrics(&a.run_dir)?);
    if let Some(line) = plot_cmd::standing(&a.run_dir, &curve, &metrics)? {
        println!("{line}");
    }
    Ok(())
}

fn snapshot_cmd(a: SnapshotArgs) -> Result<()> {
    let s = gdrf_core::train::snapshot::snapshot(&a.run_dir, &a.out)?;
    println!(
        "{}: the checkpoint of step {}, config, metrics, curve and {} evaluation frames ({} files) from {}",
        a.out.display(),
        s.step,
        s.frames,
        s.files,
        a.run_dir.display()
    );
    Ok(())
}

fn interpolate_cmd(a: InterpolateArgs) -> Result<()> {
    let header = gdrf_core::checkpoint::save_interpolated(&a.from, &a.to, a.t, &a.t_for, &a.out)?;
    println!(
        "wrote {}: from {}, to {}; {}",
        a.out.display(),
        a.from.display(),
        a.to.display(),
        header.info.get("interpolated").map_or("", String::as_str)
    );
    Ok(())
}

fn dataset(cmd: DatasetCommand) -> Result<()> {
    match cmd {
        DatasetCommand::Synth(a) => synth_cmd(a),
        DatasetCommand::Swap(a) => swap_cmd(a),
        DatasetCommand::Inspect(a) => inspect_cmd(a),
        DatasetCommand::Prepare(a) => prepare_cmd(a),
    }
}

fn synth_cmd(a: SynthArgs) -> Result<()> {
    if a.out.join(data::METADATA_FILE).exists() && !a.force {
        bail!("{} already holds a dataset (metadata.json); pass --force to replace it", a.out.display());
    }
    let camera = a.camera.camera();
    let opts = SynthOptions {
        category: a.category,
        count: a.count,
        resolution: a.resolution,
        seed: a.seed,
        supersample: a.supersample,
        views_per_object: a.views_per_object,
        held_out_fraction: a.held_out,
        shadows: !a.no_shadows,
        camera,
    };
    opts.validate().context("invalid `dataset synth` options")?;
    let threads = data::thread_count(a.threads);
    let pb = progress::bar(a.count as u64, "images", false);
    let start = Instant::now();
    let meta = synth::generate(&a.out, &opts, threads, &|e| progress::follow(&pb, e))?;
    pb.finish_and_clear();
    let secs = start.elapsed().as_secs_f64();
    let held = meta.images.iter().filter(|r| r.split == data::Split::HeldOut).count();
    println!(
        "wrote {} images of {}×{} to {} in {:.1} s ({:.1} images/s, {} threads); {} held out",
        meta.images.len(),
        a.resolution,
        a.resolution,
        a.out.display(),
        secs,
        meta.images.len() as f64 / secs,
        threads,
        held
    );
    if a.contact_sheet {
        let path = a.out.join("contact-sheet.png");
        write_contact_sheet(&a.out, Layout::Synth, a.resolution, &path)?;
        println!("contact sheet: {}", path.display());
    }
    Ok(())
}

/// 64 random images of a dataset (decoded without touching its cache) in an 8 × 8 grid.
fn write_contact_sheet(dir: &Path, layout: Layout, res: usize, out: &Path) -> Result<()> {
    let mut opts = LoadOptions::new(res);
    opts.layout = layout;
    opts.cache = false;
    let ds = data::load(dir, &opts, &|_| {})?;
    save_sheet(&ds, out)
}

fn save_sheet(ds: &data::Dataset, out: &Path) -> Result<()> {
    let idx = data::sample_indices(ds.len(), 64, 0);
    let sheet = data::contact_sheet(&ds.images(), &idx, 8)?;
    gdrf_core::io::save_png(out, &sheet)?;
    Ok(())
}

fn swap_cmd(a: SwapArgs) -> Result<()> {
    let meta = Metadata::load(&a.dataset)?;
    let pose = a.pitch.zip(a.yaw);
    let img = synth::render_swap(&meta, a.shape_from, a.appearance_from, pose, a.resolution, a.supersample)?;
    let bytes = synth::encode_png(img.to_rgba8(), img.resolution)?;
    gdrf_core::paths::write_atomic(&a.out, &bytes)?;
    println!(
        "wrote {}: shape of object {} with the appearance of object {}",
        a.out.display(),
        a.shape_from,
        a.appearance_from
    );
    Ok(())
}

fn inspect_cmd(a: InspectArgs) -> Result<()> {
    let mut opts = LoadOptions::new(a.resolution);
    opts.layout = a.layout;
    opts.poses = a.poses;
    opts.require_poses = a.require_poses;
    opts.skip_bad = a.skip_bad;
    opts.split = match a.split.as_str() {
        "train" => Some(data::Split::Train),
        "held_out" => Some(data::Split::HeldOut),
        _ => None,
    };
    opts.cache = !a.no_cache;
    opts.threads = a.threads;
    let ds = load_reporting(&a.dir, &opts)?;
    if let Some(path) = a.contact_sheet {
        save_sheet(&ds, &path)?;
        println!("contact sheet: {}", path.display());
    }
    Ok(())
}

/// Loads with a progress bar and prints what was loaded, skipped and how fast.
fn load_reporting(dir: &Path, opts: &LoadOptions) -> Result<data::Dataset> {
    let pb = progress::bar(0, "images", false);
    let start = Instant::now();
    let ds =
        data::load(dir, opts, &|e| progress::follow(&pb, e)).with_context(|| format!("loading {}", dir.display()))?;
    pb.finish_and_clear();
    let secs = start.elapsed().as_secs_f64();
    for s in &ds.skipped {
        eprintln!("warning: skipped {}: {}", s.path.display(), s.reason);
    }
    if !ds.skipped.is_empty() {
        eprintln!("warning: {} file(s) skipped", ds.skipped.len());
    }
    let source = match &ds.cache {
        CacheStatus::Hit(p) => format!("read from cache {}", p.display()),
        CacheStatus::Decoded(Some(p)) => format!("decoded, cached in {}", p.display()),
        CacheStatus::Decoded(None) => "decoded (cache off)".into(),
        CacheStatus::WriteFailed(p, e) => {
            eprintln!("warning: could not write the cache {}: {e}", p.display());
            "decoded (not cached)".into()
        }
    };
    println!(
        "{}: {} images at {}×{} ({} layout), poses: {}; {source}; {:.2} s, {:.0} images/s",
        dir.display(),
        ds.len(),
        ds.resolution,
        ds.resolution,
        ds.layout.name(),
        if ds.poses.is_some() { "yes" } else { "no" },
        secs,
        ds.len() as f64 / secs
    );
    Ok(ds)
}

fn prepare_cmd(a: PrepareArgs) -> Result<()> {
    #[derive(serde::Deserialize)]
    struct Config {
        data: DataConfig,
    }
    let text = std::fs::read_to_string(&a.config).with_context(|| format!("reading {}", a.config.display()))?;
    let cfg: Config = toml::from_str(&text).with_context(|| format!("{}: invalid [data] table", a.config.display()))?;
    let mut data_cfg = cfg.data;
    // Relative paths are relative to the config file's folder.
    let base = a.config.parent().unwrap_or(Path::new("."));
    data_cfg.path = base.join(&data_cfg.path);
    data_cfg.poses = data_cfg.poses.map(|p| base.join(p));
    data_cfg.cache_dir = data_cfg.cache_dir.map(|p| base.join(p));
    let count = data_cfg.synth.as_ref().map_or(0, |s| s.count);
    let pb = progress::bar(count as u64, "images", false);
    let prepared = data_cfg.prepare(a.threads, &|e| progress::follow(&pb, e))?;
    pb.finish_and_clear();
    if prepared == Prepared::Generated {
        println!("generated the synthetic dataset in {}", data_cfg.path.display());
    }
    load_reporting(&data_cfg.path, &data_cfg.load_options(a.resolution, a.threads))?;
    Ok(())
}

#[cfg(test)]
mod quiet_tests {
    use super::Cli;
    use clap::{CommandFactory, Parser};

    #[test]
    fn every_subcommand_takes_quiet() {
        assert_eq!(gdrf_core::progress::without_quiet(&mut Cli::command()), Vec::<String>::new());
        // The flag after the subcommand, where a user adds it to an evaluation's command line.
        let cli = Cli::try_parse_from(["gdrf-train", "eval", "--generator", "g.safetensors", "--quiet"]).unwrap();
        assert!(cli.train.quiet);
        assert!(!Cli::try_parse_from(["gdrf-train", "eval", "--generator", "g.safetensors"]).unwrap().train.quiet);
    }
}
