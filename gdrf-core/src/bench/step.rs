//! `gdrf-bench step`: full training steps of a training config's stage, gdrf's
//! [`Trainer::step`] against the PyTorch reference (scripts/reference/bench_step.py) at the
//! same sizes. With `--nproc N`, data-parallel scaling on the CPU: one process of N threads
//! against N ranks of one thread each (Gloo over loopback), for both; the command starts
//! the ranks as copies of itself (`--worker`, with torchrun's variables).
use super::{median, peak_rss_mb, reference_run, spawn_ranks, Run, Timings};
use crate::data::layouts::Layout;
use crate::data::synth::SynthOptions;
use crate::data::SplitChoice;
use crate::disc::DiscConfig;
use crate::dist::{Launch, ProcessGroup};
use crate::loss::LossConfig;
use crate::nn::sine;
use crate::paths::TempDir;
use crate::train::config::{EmaConfig, OptimConfig, Precision};
use crate::train::{PatchConfig, StepReport, TrainConfig, Trainer};
use crate::{CameraConfig, Error, GeneratorConfig, Result};
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// The flags of `gdrf-bench step`.
#[derive(clap::Args)]
pub struct Options {
    /// Training config (TOML), e.g. configs/chairs-tiny.toml.
    #[arg(long)]
    pub config: PathBuf,
    /// Batch size (default: the stage's).
    #[arg(long)]
    pub batch: Option<i64>,
    /// Chunks the generator's batch is rendered in (default: the stage's; the
    /// release's per-GPU step is 4 images in 4 chunks).
    #[arg(long)]
    pub batch_split: Option<i64>,
    /// Index of the config's stage to run (its resolution, samples, batch, split).
    #[arg(long, default_value_t = 0)]
    pub stage: usize,
    /// Image side R (default: the stage's), e.g. the 128² step of a 64² stage.
    #[arg(long)]
    pub resolution: Option<i64>,
    /// The scaled-patch step with P×P patches of the R×R images (`[stages.patch] size`;
    /// default: the stage's, whole images where it has none); 0: whole images even where the
    /// stage has patches. The PyTorch reference has no such step and is then skipped.
    #[arg(long, value_name = "P")]
    pub patch: Option<i64>,
    /// The training-time occupancy grid (`[occupancy]` with its defaults): gdrf's steps clip
    /// their rays to it; the grid's refresh is timed on its own (phase `occupancy refresh`,
    /// due every `occupancy.every` steps). The reference has none, and is then skipped.
    #[arg(long)]
    pub occupancy: bool,
    /// Start gdrf's generator from this generator file (`init_generator`), e.g.
    /// models/chairs-campaign/generator.safetensors, so that the step renders, and a grid
    /// sees, a trained model's empty space; its [generator] replaces the config's.
    #[arg(long, value_name = "FILE")]
    pub init_generator: Option<PathBuf>,
    /// Timed steps per implementation (the median is reported).
    #[arg(long, default_value_t = 3)]
    pub steps: usize,
    /// Untimed steps first.
    #[arg(long, default_value_t = 1)]
    pub warmup: usize,
    /// Skip the PyTorch reference (report gdrf alone).
    #[arg(long)]
    pub no_reference: bool,
    /// cpu, cuda or cuda:N; both implementations run there (default: cpu).
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// float32, bfloat16 or auto (bfloat16 on a CPU with bfloat16 instructions, float32
    /// elsewhere) (gdrf: `precision`; the reference: bfloat16 autocast).
    /// Default: the config's.
    #[arg(long)]
    pub precision: Option<String>,
    /// Data-parallel scaling on the CPU: time the step as N ranks of one thread each (the
    /// global batch split among them, Gloo over loopback) beside one process of N threads,
    /// gdrf's and the reference's (torch.distributed, gradients all-reduced as
    /// DistributedDataParallel does). Writes …-nproc<N>.json.
    #[arg(long, default_value_t = 1)]
    pub nproc: usize,
    /// Folder for step-<config>-stage<I>-b<batch>[-r<R>][-p<P>][-<device>][-bf16][-nproc<N>].json
    /// and .png.
    #[arg(long, default_value = "bench")]
    pub out_dir: PathBuf,
    /// Run as one rank of --nproc (set by the command itself for the processes it starts).
    #[arg(long, hide = true)]
    pub worker: bool,
}

/// What the step benchmark ran: the stage's sizes, the timing protocol and the config's
/// sections the reference is given.
#[derive(Serialize)]
pub struct Settings {
    pub config: String,
    pub stage: usize,
    pub resolution: i64,
    pub num_steps: usize,
    pub batch_size: i64,
    pub batch_split: i64,
    pub regions: i64,
    /// The scaled-patch step's patch side (absent: whole images).
    pub patch: Option<i64>,
    pub warmup_steps: usize,
    pub timed_steps: usize,
    pub device: String,
    /// `float32` or `bfloat16`.
    pub precision: &'static str,
    pub timed_steps_r1: &'static str,
    pub real_images: &'static str,
    pub g_lr: f64,
    pub d_lr: f64,
    pub generator: GeneratorConfig,
    pub discriminator: DiscConfig,
    pub loss: LossConfig,
    pub optim: OptimConfig,
    pub ema: EmaConfig,
    pub camera: CameraConfig,
    /// What the comparison leaves out (the stage's patches, pose distribution, …).
    pub notes: Vec<String>,
}

/// Runs gdrf and the reference, prints the table and writes
/// step-<config>-stage<I>-b<batch>[-<device>][-bf16][-nproc<N>].json and .png into
/// `--out-dir` (with `--worker`, one rank of `--nproc`: then no report).
pub fn run(a: &Options) -> Result<Option<Timings<Settings>>> {
    let (config, stage, steps, warmup) = (&a.config, a.stage, a.steps, a.warmup);
    if steps == 0 {
        return Err(Error::Invalid("--steps must be at least 1".into()));
    }
    if a.worker {
        return worker(a).map(|()| None);
    }
    if a.nproc == 0 || (a.nproc > 1 && a.device != "cpu") {
        return Err(Error::Invalid("--nproc must be at least 1, and more than 1 only with --device cpu".into()));
    }
    let tmp = TempDir::new("bench-step")?;
    let (cfg, notes) = step_config(a, &tmp.0)?;
    let bf16 = cfg.precision.on(crate::device::select(&a.device)?) == Precision::Bfloat16;
    for n in &notes {
        eprintln!("note: {n}");
    }
    let st = cfg.stages[0].clone();
    let (b, res, n) = (st.batch_size, st.resolution, st.num_steps);
    let patch = st.patch.as_ref().map(|p| p.size);
    let stem = config.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "config".into());
    let r1 = if cfg.loss.r1_gamma == 0.0 { "R1 off".to_string() } else { "R1 due".to_string() };
    let precision = if bf16 { "bfloat16" } else { "float32" };
    let image = match patch {
        Some(p) => format!("{p}² scaled patches of {res}²"),
        None => format!("{res}²"),
    };
    let title = format!(
        "Training step (D + G, Adam, EMA), {stem} stage {stage}: batch {b} (split {}), {image}, {n}+{n} samples, {r1}, {} {precision}",
        st.batch_split, a.device,
    );
    eprintln!("{title}\nrunning gdrf ({warmup} warm-up + {steps} timed steps) …");
    let settings = settings(a, &cfg, notes, precision);
    let mut ref_args = reference_args(&cfg, warmup, steps)?;
    ref_args.push(format!("--device={}", a.device));
    if bf16 {
        ref_args.push("--bf16".into());
    }
    let runs = measure_all(a, cfg, &tmp.0, &ref_args, bf16)?;
    let title = print_table(title, &runs, a.nproc);
    let machine = if a.device == "cpu" {
        format!("{} CPU threads", runs[0].threads)
    } else {
        format!("{}, {} CPU threads", a.device, runs[0].threads)
    };
    let n = a.nproc;
    let mut phases = if n > 1 { vec!["step", "allreduce"] } else { vec!["step"] };
    if a.occupancy {
        phases.push(REFRESH);
    }
    let doc = Timings { title, machine, settings: Some(settings), phases, runs };
    let mut name = format!("step-{stem}-stage{stage}-b{b}");
    if a.resolution.is_some() {
        name += &format!("-r{res}");
    }
    if let Some(p) = patch {
        name += &format!("-p{p}");
    }
    if a.init_generator.is_some() {
        name += "-init";
    }
    if a.occupancy {
        name += "-occ";
    }
    if a.device != "cpu" {
        name += &format!("-{}", a.device.replace(':', ""));
    }
    if bf16 {
        name += "-bf16";
    }
    if n > 1 {
        name += &format!("-nproc{n}");
    }
    doc.write(&a.out_dir, &name)?;
    Ok(Some(doc))
}

/// What the benchmark ran, for its JSON: the stage's sizes, the step counts, the device and
/// precision, and the config's sections that shape a step.
fn settings(a: &Options, cfg: &TrainConfig, notes: Vec<String>, precision: &'static str) -> Settings {
    let st = &cfg.stages[0];
    let (g_lr, d_lr) = cfg.learning_rates(0);
    Settings {
        config: a.config.display().to_string(),
        stage: a.stage,
        resolution: st.resolution,
        num_steps: st.num_steps,
        batch_size: st.batch_size,
        batch_split: st.batch_split,
        regions: st.regions,
        patch: st.patch.as_ref().map(|p| p.size),
        warmup_steps: a.warmup,
        timed_steps: a.steps,
        device: a.device.clone(),
        precision,
        timed_steps_r1: "timed steps run at step indices where R1 is due (multiples of loss.r1_interval)",
        real_images:
            "gdrf: a 64-image procedural dataset at the stage's resolution; reference: random images and poses",
        g_lr,
        d_lr,
        generator: cfg.generator.clone(),
        discriminator: cfg.discriminator.clone(),
        loss: cfg.loss.clone(),
        optim: cfg.optim.clone(),
        ema: cfg.ema.clone(),
        camera: cfg.camera.clone(),
        notes,
    }
}

/// The runs compared: in one process, gdrf (and on the CPU in float32 gdrf with libtorch's
/// sine) and the reference; with `--nproc` n > 1, gdrf and the reference each as one process
/// of n threads and as n ranks of one thread.
fn measure_all(a: &Options, cfg: TrainConfig, tmp: &Path, ref_args: &[String], bf16: bool) -> Result<Vec<Run>> {
    let (warmup, steps) = (a.warmup, a.steps);
    let cores = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    let n = a.nproc;
    let cfg_patch = cfg.stages[0].patch.clone();
    let cfg_occupancy = cfg.occupancy.clone();
    let mut runs = Vec::new();
    if n == 1 {
        runs.push(measure(cfg.clone(), &tmp.join("run"), warmup, steps, cores, None)?);
        if a.device == "cpu" && !bf16 && sine::vectorised() {
            // The same steps with libtorch's float32 sine (MKL), which SLEEF's replaced.
            eprintln!("running gdrf again with libtorch's sine ({warmup} warm-up + {steps} timed steps) …");
            let dir = tmp.join("run-libtorch-sine");
            let mut r = sine::with_libtorch_sine(|| measure(cfg, &dir, warmup, steps, cores, None))?;
            r.implementation = "gdrf with libtorch's sine".into();
            runs.push(r);
        }
        if !a.no_reference && cfg_patch.is_none() && cfg_occupancy.is_none() {
            runs.push(reference_run("bench_step.py", ref_args)?);
        }
    } else {
        let mut alone = measure(cfg, &tmp.join("run"), warmup, steps, n, None)?;
        alone.implementation = format!("gdrf, 1 process × {n} threads");
        runs.push(alone);
        eprintln!("running gdrf as {n} ranks of 1 thread …");
        let mut ranks = ranks(a)?;
        ranks.implementation = format!("gdrf, {n} ranks × 1 thread");
        runs.push(ranks);
        if !a.no_reference && cfg_patch.is_none() && cfg_occupancy.is_none() {
            for (world, threads) in [(1, n), (n, 1)] {
                let mut args = ref_args.to_vec();
                args.extend([format!("--threads={threads}"), format!("--world={world}")]);
                let mut r = reference_run("bench_step.py", &args)?;
                r.implementation = if world == 1 {
                    format!("PyTorch reference, 1 process × {n} threads")
                } else {
                    format!("PyTorch reference (torch.distributed), {n} ranks × 1 thread")
                };
                runs.push(r);
            }
        }
    }
    Ok(runs)
}

/// Prints the runs' table under `title`: each run's median step, images a second and peak
/// memory, then each against gdrf's (one process) or the ranks' scaling efficiency (`n` > 1,
/// which the returned title then states).
fn print_table(title: String, runs: &[Run], n: usize) -> String {
    let per_second = |r: &Run| r.images_per_second.unwrap_or(f64::NAN);
    println!("{title}");
    let w = runs.iter().map(|r| r.implementation.chars().count()).max().unwrap_or(0).max(20) + 7;
    println!("{:<w$}{:>16}{:>12}{:>12}", "", "median s/step", "images/s", "peak MB");
    for r in runs {
        println!("{:<w$}{:>16.3}{:>12.2}{:>12.0}", r.implementation, r.median("step"), per_second(r), r.peak_rss_mb);
    }
    if n == 1 {
        // Every other run against gdrf's (peak memory is the process's so far).
        for y in &runs[1..] {
            println!(
                "{:<w$}{:>15.2}×{:>11.2}×{:>11.2}×",
                format!("{} / gdrf", y.implementation),
                y.median("step") / runs[0].median("step"),
                per_second(y) / per_second(&runs[0]),
                y.peak_rss_mb / runs[0].peak_rss_mb
            );
        }
        return title;
    }
    // Scaling efficiency: the ranks' throughput over one process's on the same cores.
    let mut said = Vec::new();
    for pair in runs.chunks(2) {
        let (one, many) = (&pair[0], &pair[1]);
        let efficiency = per_second(many) / per_second(one);
        let share = many.median("allreduce") / many.median("step");
        println!(
            "{}: scaling efficiency {efficiency:.2}, all-reduce {:.0}% of the ranks' step",
            many.implementation,
            share * 100.0
        );
        said.push(format!(
            "{} {efficiency:.2} ({:.0}% all-reduce)",
            if said.is_empty() { "gdrf" } else { "reference" },
            share * 100.0
        ));
    }
    format!("{title}; {n} ranks × 1 thread vs 1 process × {n} threads, efficiency: {}", said.join(", "))
}

/// One rank of `--nproc`: the same stage and timing protocol on its share of the batch,
/// one thread; rank 0 prints its [`Run`] as JSON.
fn worker(a: &Options) -> Result<()> {
    let launch = Launch::from_env()?;
    let tmp = TempDir::new("bench-step-rank")?;
    let (cfg, _) = step_config(a, &tmp.0)?;
    let group = ProcessGroup::join(&launch, Duration::from_secs(600))?;
    let run = measure(cfg, &tmp.0.join("run"), a.warmup, a.steps, 1, Some(group))?;
    if launch.rank == 0 {
        println!("{}", serde_json::to_string(&run)?);
    }
    Ok(())
}

/// Starts the `--nproc` ranks (this program with `--worker`) and reads rank 0's [`Run`].
fn ranks(a: &Options) -> Result<Run> {
    let mut args: Vec<_> = std::env::args_os().skip(1).collect();
    args.push("--worker".into());
    let out = spawn_ranks(a.nproc, &args)?;
    serde_json::from_slice(&out).map_err(|e| Error::Distributed(format!("rank 0 printed no timings: {e}")))
}

/// The config of `gdrf-bench step`: stage `--stage` of the file as the only stage (batch
/// overridden), on `--device` and `--precision`, never sampling or rolling back, training
/// on a small procedural dataset under `tmp`. Also returns notes on what the comparison
/// leaves out.
fn step_config(a: &Options, tmp: &Path) -> Result<(TrainConfig, Vec<String>)> {
    let (path, stage, batch, split) = (&a.config, a.stage, a.batch, a.batch_split);
    let mut cfg = TrainConfig::load(path)?;
    if let Some(p) = &a.precision {
        cfg.precision = match p.as_str() {
            "float32" => Precision::Float32,
            "bfloat16" => Precision::Bfloat16,
            "auto" => Precision::Auto,
            other => return Err(Error::Invalid(format!("--precision {other}: expected float32, bfloat16 or auto"))),
        };
    }
    let n = cfg.stages.len();
    if stage >= n {
        return Err(Error::Invalid(format!("--stage {stage}: {} has {n} stage(s), numbered from 0", path.display())));
    }
    let mut notes = Vec::new();
    let mut st = cfg.stages[stage].clone();
    st.from_step = 0;
    if let Some(b) = batch {
        if b < 1 {
            return Err(Error::Invalid("--batch must be at least 1".into()));
        }
        st.batch_size = b;
    }
    if let Some(k) = split {
        if k < 1 || st.batch_size % k != 0 {
            return Err(Error::Invalid(format!("--batch-split {k} must divide the batch {}", st.batch_size)));
        }
        st.batch_split = k;
    } else if batch.is_some() {
        let b = st.batch_size;
        if b % st.batch_split != 0 {
            notes.push(format!("batch_split {} does not divide --batch {b}: using batch_split 1", st.batch_split));
            st.batch_split = 1;
        }
    }
    if let Some(r) = a.resolution {
        st.resolution = r;
    }
    match a.patch {
        Some(0) => st.patch = None,
        // The end of the annealing: a step costs the same at any scale.
        Some(p) => st.patch = Some(PatchConfig { size: p, anneal_images: 0, ..PatchConfig::default() }),
        None => {}
    }
    if st.patch.is_some() {
        notes.push("the scaled-patch step: the PyTorch reference has none, and is not run".into());
    }
    if a.occupancy {
        cfg.occupancy = Some(Default::default());
        notes.push("the training-time occupancy grid: the PyTorch reference has none, and is not run".into());
    }
    if let Some(path) = &a.init_generator {
        let loaded = crate::checkpoint::load_generator(path, tch::Device::Cpu, tch::Kind::Float)?;
        cfg.generator = loaded.generator.cfg.clone();
        cfg.init_generator = Some(path.clone());
        notes.push(format!("gdrf's generator starts from {}", path.display()));
    }
    if st.regions > 1 {
        notes.push(format!(
            "gdrf runs the two-pass patch step ({} regions); the reference renders whole images",
            st.regions
        ));
    }
    if cfg.camera.distribution != crate::PoseDistribution::Uniform {
        notes.push(format!("poses: gdrf draws {:?}, the reference uniform", cfg.camera.distribution));
    }
    if !cfg.render.hierarchical {
        notes.push("render.hierarchical is off; the reference always adds importance samples".into());
    }
    if cfg.generator.deform_scale != 1.0 {
        notes.push(format!(
            "generator.deform_scale {} is not modelled by the reference (1)",
            cfg.generator.deform_scale
        ));
    }
    if cfg.loss.latent_weight != 0.0 {
        notes.push("loss.latent_weight is not 0; the reference has no latent loss".into());
    }
    let resolution = st.resolution as usize;
    cfg.stages = vec![st];
    cfg.device = a.device.clone();
    cfg.schedule.total_steps = i64::MAX / 2;
    cfg.schedule.sample_interval = 0;
    cfg.debug = Default::default();
    // No checkpoint to go back to: a non-finite step is reported, never rolled back.
    cfg.guard.rollback_after = i64::MAX;
    let synth = cfg.data.synth.clone().unwrap_or_default();
    cfg.data.path = tmp.join("data");
    cfg.data.layout = Layout::Auto;
    cfg.data.poses = None;
    cfg.data.require_poses = true;
    cfg.data.skip_bad = false;
    cfg.data.split = SplitChoice::Train;
    cfg.data.cache = false;
    cfg.data.cache_dir = None;
    cfg.data.synth =
        Some(SynthOptions { count: 64, resolution, supersample: 1, shadows: false, held_out_fraction: 0.0, ..synth });
    cfg.validate()?;
    Ok((cfg, notes))
}

/// `warmup` untimed then `steps` timed training steps of gdrf on `threads` threads, alone
/// or as a rank of `group` (the ranks start each step together; the time in collectives
/// is the `allreduce` phase). Timed steps run at step indices where R1 is due (the
/// counter is moved up to the next multiple of `r1_interval`; a single stage has no
/// fade-in, so nothing else depends on it).
fn measure(
    mut cfg: TrainConfig,
    run_dir: &Path,
    warmup: usize,
    steps: usize,
    threads: usize,
    group: Option<ProcessGroup>,
) -> Result<Run> {
    tch::set_num_threads(threads as i32);
    cfg.threads = threads;
    let mut trainer = Trainer::new(cfg, run_dir)?;
    let t0 = Instant::now();
    trainer.prepare_data(&|_| {})?;
    if let Some(g) = group {
        trainer.join_group(g)?;
    }
    let res = trainer.cfg.stages[0].resolution;
    let n = trainer.dataset(res)?.len();
    eprintln!("procedural dataset: {n} images at {res}² ({:.1} s)", t0.elapsed().as_secs_f64());
    let report = |r: &StepReport, what: &str| {
        let bad = if r.d_skipped || r.g_skipped { " (non-finite: update skipped)" } else { "" };
        eprintln!("gdrf {what} {}: {:.2} s{bad}", r.step, r.seconds);
    };
    for _ in 0..warmup {
        trainer.barrier()?;
        report(&trainer.step()?, "warm-up step");
    }
    let every = trainer.cfg.loss.r1_interval.max(1);
    let (mut samples, mut comm) = (Vec::with_capacity(steps), Vec::with_capacity(steps));
    for _ in 0..steps {
        let s = trainer.progress.step;
        trainer.progress.step = (s + every - 1) / every * every;
        trainer.barrier()?;
        let before = trainer.comm_seconds();
        let r = trainer.step()?;
        comm.push(trainer.comm_seconds() - before);
        report(&r, "step");
        samples.push(r.seconds);
    }
    let b = trainer.cfg.stages[0].batch_size as f64;
    let med = median(&samples);
    let mut median_s: BTreeMap<String, f64> =
        [("step".to_string(), med), ("allreduce".to_string(), median(&comm))].into();
    let mut samples_s: BTreeMap<String, Vec<f64>> =
        [("step".to_string(), samples), ("allreduce".to_string(), comm)].into();
    let mut other = serde_json::Map::new();
    if trainer.cfg.occupancy.is_some() {
        let refresh: Vec<f64> = (0..steps)
            .map(|_| {
                let t = Instant::now();
                trainer.refresh_grid_now().map(|()| t.elapsed().as_secs_f64())
            })
            .collect::<Result<_>>()?;
        eprintln!("gdrf occupancy refresh: {:.2} s (median of {steps})", median(&refresh));
        median_s.insert(REFRESH.into(), median(&refresh));
        samples_s.insert(REFRESH.into(), refresh);
        let grid = trainer.occupancy_grid().expect("a refreshed grid");
        other.insert("occupied_fraction".into(), grid.occupied_fraction().into());
        other.insert("refresh_queries".into(), grid.grid.evaluated.into());
    }
    Ok(Run {
        implementation: "gdrf (tch)".into(),
        threads,
        median_s,
        samples_s,
        peak_rss_mb: peak_rss_mb(),
        images_per_second: Some(b / med),
        other,
    })
}

/// The phase timing one refresh of the training-time occupancy grid.
const REFRESH: &str = "occupancy refresh";

/// The reference's flags for the same step (scripts/reference/bench_step.py).
fn reference_args(cfg: &TrainConfig, warmup: usize, steps: usize) -> Result<Vec<String>> {
    let st = &cfg.stages[0];
    let (g_lr, d_lr) = cfg.learning_rates(0);
    // The stage's own settings, as the trainer runs it: its learning rates and pose weight.
    let loss = cfg.loss_at(0);
    let (g, l, o, c) = (&cfg.generator, &loss, &cfg.optim, &cfg.camera);
    let list = |v: &[String]| v.join(",");
    let variant = serde_json::to_value(l.reg.variant)
        .map_err(|e| Error::Invalid(e.to_string()))?
        .as_str()
        .unwrap_or("release")
        .to_string();
    let mut a: Vec<(&str, String)> = vec![
        ("resolution", st.resolution.to_string()),
        ("num-steps", st.num_steps.to_string()),
        ("batch", st.batch_size.to_string()),
        ("batch-split", st.batch_split.to_string()),
        ("latent-dim", g.latent_dim.to_string()),
        ("hidden-dim", g.hidden_dim.to_string()),
        ("mapping-hidden-dim", g.mapping_hidden_dim.to_string()),
        ("trunk-layers", g.trunk_layers.to_string()),
        ("color-layers", g.colour_layers.to_string()),
        ("deform-layers", g.deform_layers.to_string()),
        ("correct-scale", g.correct_scale.to_string()),
        ("disc-channels", list(&cfg.discriminator.channels.iter().map(|c| c.to_string()).collect::<Vec<_>>())),
        ("r1-gamma", l.r1_gamma.to_string()),
        ("r1-interval", l.r1_interval.to_string()),
        ("pose-weight", l.pose_weight.to_string()),
        (
            "reg-weights",
            list(&[l.reg.correction, l.reg.smoothness, l.reg.rigidity, l.reg.normal].map(|w| w.to_string())),
        ),
        ("reg-variant", variant),
        ("reg-ray-ratio", l.reg.ray_ratio.to_string()),
        ("reg-near-ratio", l.reg.near_ratio.to_string()),
        ("reg-sample-ratio", l.reg.sample_ratio.to_string()),
        ("topk-interval", l.topk_interval.to_string()),
        ("topk-floor", l.topk_floor.to_string()),
        ("g-lr", g_lr.to_string()),
        ("d-lr", d_lr.to_string()),
        ("betas", list(&[o.beta1.to_string(), o.beta2.to_string()])),
        ("adam-eps", o.eps.to_string()),
        ("grad-clip", o.grad_clip.to_string()),
        ("ema-decay", cfg.ema.decay.to_string()),
        ("fov", c.fov_deg.to_string()),
        ("ray-start", c.ray_start.to_string()),
        ("ray-end", c.ray_end.to_string()),
        ("h-mean", c.h_mean.to_string()),
        ("h-std", c.h_std.to_string()),
        ("v-mean", c.v_mean.to_string()),
        ("v-std", c.v_std.to_string()),
        ("warmup", warmup.to_string()),
        ("steps", steps.to_string()),
        ("seed", cfg.seed.to_string()),
    ];
    if !cfg.ema.warmup {
        a.push(("no-ema-warmup", String::new()));
    }
    // --key=value, so that negative numbers are not taken for options.
    Ok(a.into_iter().map(|(k, v)| if v.is_empty() { format!("--{k}") } else { format!("--{k}={v}") }).collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        options: Options,
    }

    /// The patch side of the one stage `gdrf-bench step` runs with `args` on the campaign's
    /// CPU config, whose 64² stage (index 2) has 32² patches.
    fn patch_of(args: &[&str]) -> Option<i64> {
        let config = crate::paths::repo_root().join("configs/chairs-campaign-cpu.toml");
        let mut argv = vec!["gdrf-bench", "--config", config.to_str().unwrap(), "--stage", "2"];
        argv.extend_from_slice(args);
        let a = Cli::try_parse_from(argv).unwrap().options;
        let (cfg, _) = step_config(&a, Path::new("unused")).unwrap();
        cfg.stages[0].patch.as_ref().map(|p| p.size)
    }

    /// The reference runs the benchmarked stage's own pose weight, as the trainer does: the
    /// campaign's [loss] weight in its stage 2, the weight stage 3 sets there.
    #[test]
    fn reference_gets_the_stages_pose_weight() {
        let config = crate::paths::repo_root().join("configs/chairs-campaign-cpu.toml");
        let weight = |stage: &str| {
            let argv = ["gdrf-bench", "--config", config.to_str().unwrap(), "--stage", stage];
            let (cfg, _) = step_config(&Cli::try_parse_from(argv).unwrap().options, Path::new("unused")).unwrap();
            let args = reference_args(&cfg, 1, 1).unwrap();
            args.into_iter().find(|a| a.starts_with("--pose-weight=")).expect("a pose weight")
        };
        assert_eq!([weight("2"), weight("3")], ["--pose-weight=54".to_string(), "--pose-weight=38.1".to_string()]);
    }

    #[test]
    fn patch_flag_keeps_replaces_or_drops_the_stages_patches() {
        assert_eq!(patch_of(&[]), Some(32));
        assert_eq!(patch_of(&["--patch", "16"]), Some(16));
        assert_eq!(patch_of(&["--patch", "0"]), None);
    }
}
