//! gdrf-bench: benchmarks run side by side with the PyTorch reference (scripts/reference/),
//! printing medians and ratios and writing JSON and a bar chart.
use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};
use gdrf_core::bench::{median, peak_rss_mb};
use gdrf_core::camera::Poses;
use gdrf_core::data::layouts::Layout;
use gdrf_core::data::synth::SynthOptions;
use gdrf_core::data::SplitChoice;
use gdrf_core::disc::Discriminator;
use gdrf_core::loss::{LossConfig, Schedule};
use gdrf_core::paths::TempDir;
use gdrf_core::render::{Noise, Renderer};
use gdrf_core::train::config::Precision;
use gdrf_core::train::{discriminator_pass, generator_pass, FakeBatch, TrainConfig, Trainer};
use gdrf_core::{device, CameraConfig, Generator, GeneratorConfig, RenderConfig};
use serde_json::json;
use std::path::{Path, PathBuf};
use std::time::Instant;
use tch::{nn, Kind, Tensor};

#[derive(Parser)]
#[command(version, about = "Benchmarks of gdrf against the PyTorch reference, in one run.")]
struct Cli {
    #[command(subcommand)]
    command: Bench,
}

#[derive(Subcommand)]
enum Bench {
    /// One generator loss + backward and one discriminator loss + backward (release
    /// settings: regularisers on, R1 every step). The batch is processed in
    /// `--batch-split` chunks for G, as the release does, so that one 64² image's graph
    /// (about 12 GB in float32) fits in memory.
    Losses {
        #[arg(long, default_value_t = 4)]
        batch: i64,
        #[arg(long, default_value_t = 4)]
        batch_split: i64,
        #[arg(long, default_value_t = 64)]
        resolution: i64,
        /// Coarse samples per ray (the importance pass adds as many).
        #[arg(long, default_value_t = 36)]
        steps: usize,
        /// Timed repetitions per implementation (medians are reported).
        #[arg(long, default_value_t = 1)]
        repeats: usize,
        /// Skip the PyTorch reference (report gdrf alone).
        #[arg(long)]
        no_reference: bool,
        /// Folder for losses.json and losses.png.
        #[arg(long, default_value = "bench")]
        out_dir: PathBuf,
    },
    /// Full training steps (D step, G step, clipping, Adam, EMA) of a training config's
    /// stage, gdrf's `Trainer::step` against the PyTorch reference at the same sizes, on
    /// the CPU or a GPU (`--device`), in float32 or bfloat16. Real images come from a small procedural dataset generated in a temporary
    /// folder (the reference uses random images). Timed steps are steps where R1 is due.
    Step {
        /// Training config (TOML), e.g. configs/chairs-tiny.toml.
        #[arg(long)]
        config: PathBuf,
        /// Batch size (default: the stage's).
        #[arg(long)]
        batch: Option<i64>,
        /// Chunks the generator's batch is rendered in (default: the stage's; the
        /// release's per-GPU step is 4 images in 4 chunks).
        #[arg(long)]
        batch_split: Option<i64>,
        /// Index of the config's stage to run (its resolution, samples, batch, split).
        #[arg(long, default_value_t = 0)]
        stage: usize,
        /// Timed steps per implementation (the median is reported).
        #[arg(long, default_value_t = 3)]
        steps: usize,
        /// Untimed steps first.
        #[arg(long, default_value_t = 1)]
        warmup: usize,
        /// Skip the PyTorch reference (report gdrf alone).
        #[arg(long)]
        no_reference: bool,
        /// cpu, cuda or cuda:N; both implementations run there (default: cpu).
        #[arg(long, default_value = "cpu")]
        device: String,
        /// float32 or bfloat16 (gdrf: `precision`; the reference: bfloat16 autocast).
        /// Default: the config's.
        #[arg(long)]
        precision: Option<String>,
        /// Folder for step-<config>-stage<I>-b<batch>[-<device>][-bf16].json and .png.
        #[arg(long, default_value = "bench")]
        out_dir: PathBuf,
    },
}

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run_reference(script: &str, args: &[String]) -> Result<serde_json::Value> {
    Ok(gdrf_core::bench::run_reference(script, args)?)
}

/// Writes `OUT_DIR/<name>.json` atomically and its bar chart `<name>.png`.
fn write_report(out_dir: &Path, name: &str, doc: &serde_json::Value) -> Result<()> {
    std::fs::create_dir_all(out_dir).with_context(|| format!("creating {}", out_dir.display()))?;
    let json_path = out_dir.join(format!("{name}.json"));
    gdrf_core::paths::write_atomic(&json_path, serde_json::to_string_pretty(doc)?.as_bytes())?;
    let png = out_dir.join(format!("{name}.png"));
    gdrf_core::bench::run_script("plot_bench.py", &[&json_path, &png])?;
    println!("wrote {} and {}", json_path.display(), png.display());
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn bench_losses(b: i64, split: i64, res: i64, steps: usize, repeats: usize) -> Result<serde_json::Value> {
    let threads = device::init_threads();
    let gvs = nn::VarStore::new(tch::Device::Cpu);
    let gen = gdrf_core::rng::with_global_seed(0, || Generator::new(&gvs.root(), &GeneratorConfig::default()))?;
    let mut dvs = nn::VarStore::new(tch::Device::Cpu);
    let disc = Discriminator::new(&dvs.root());
    let camera = CameraConfig::chair();
    let config = RenderConfig { num_steps: steps, ..Default::default() };
    let renderer = Renderer::new(&gen, &camera, &config)?;
    let cfg = LossConfig::default();
    let at = Schedule { step: 0, alpha: 1.0 };
    let chunk = b / split;
    let latent = gen.cfg.latent_dim as i64;
    let mut t: std::collections::BTreeMap<&str, Vec<f64>> = Default::default();
    let zero = |vs: &nn::VarStore| {
        for (_, mut v) in vs.variables() {
            if v.grad().defined() {
                v.zero_grad();
            }
        }
    };
    for _ in 0..repeats {
        zero(&gvs);
        zero(&dvs);
        // The generator step leaves D frozen: no D parameter gradients are computed.
        dvs.freeze();
        let (mut fwd, mut bwd) = (0.0, 0.0);
        for _ in 0..split {
            let t0 = Instant::now();
            let z = Tensor::randn([chunk, latent], (Kind::Float, tch::Device::Cpu));
            let poses = Poses::sample(&camera, chunk, Kind::Float, tch::Device::Cpu);
            let lat = gen.latents(&z, &z, None);
            let noise = Noise::default();
            let fake = FakeBatch { latents: &lat, poses: &poses, z: None, resolution: res, regions: 1, noise: &noise };
            let loss = generator_pass(&renderer, &disc, &fake, None, at, &cfg)?;
            let t1 = Instant::now();
            loss.total.backward();
            fwd += (t1 - t0).as_secs_f64();
            bwd += t1.elapsed().as_secs_f64();
        }
        t.entry("g_forward").or_default().push(fwd);
        t.entry("g_backward").or_default().push(bwd);
        dvs.unfreeze();

        zero(&dvs);
        let t0 = Instant::now();
        let z = Tensor::randn([b, latent], (Kind::Float, tch::Device::Cpu));
        let poses = Poses::sample(&camera, b, Kind::Float, tch::Device::Cpu);
        let lat = tch::no_grad(|| gen.latents(&z, &z, None));
        let noise = Noise::default();
        let fake = FakeBatch { latents: &lat, poses: &poses, z: None, resolution: res, regions: 1, noise: &noise };
        let real = Tensor::rand([b, 3, res, res], (Kind::Float, tch::Device::Cpu)) * 2.0 - 1.0;
        let real_poses = Poses::sample(&camera, b, Kind::Float, tch::Device::Cpu).stacked();
        let loss = discriminator_pass(&renderer, &disc, &real, Some(&real_poses), &fake, at, &cfg)?;
        let t1 = Instant::now();
        loss.total.backward();
        t.entry("d_forward").or_default().push((t1 - t0).as_secs_f64());
        t.entry("d_backward").or_default().push(t1.elapsed().as_secs_f64());
    }
    let med: serde_json::Map<String, serde_json::Value> =
        t.iter().map(|(k, v)| (k.to_string(), json!(median(v)))).collect();
    Ok(json!({
        "implementation": "gdrf (tch)",
        "threads": threads,
        "median_s": med,
        "samples_s": t,
        "peak_rss_mb": peak_rss_mb(),
    }))
}

/// The config of `gdrf-bench step`: stage `stage` of the file as the only stage (batch
/// overridden), on `target`'s device and precision, never sampling or rolling back, training on a small
/// procedural dataset under `tmp`. Also returns notes on what the comparison leaves out.
fn step_config(
    path: &Path,
    stage: usize,
    batch: Option<i64>,
    split: Option<i64>,
    target: &StepTarget,
    tmp: &Path,
) -> Result<(TrainConfig, Vec<String>)> {
    let mut cfg = TrainConfig::load(path)?;
    if let Some(p) = &target.precision {
        cfg.precision = match p.as_str() {
            "float32" => Precision::Float32,
            "bfloat16" => Precision::Bfloat16,
            other => bail!("--precision {other}: expected float32 or bfloat16"),
        };
    }
    let n = cfg.stages.len();
    if stage >= n {
        bail!("--stage {stage}: {} has {n} stage(s), numbered from 0", path.display());
    }
    let mut notes = Vec::new();
    let mut st = cfg.stages[stage].clone();
    st.from_step = 0;
    if let Some(b) = batch {
        if b < 1 {
            bail!("--batch must be at least 1");
        }
        st.batch_size = b;
    }
    if let Some(k) = split {
        if k < 1 || st.batch_size % k != 0 {
            bail!("--batch-split {k} must divide the batch {}", st.batch_size);
        }
        st.batch_split = k;
    } else if batch.is_some() {
        let b = st.batch_size;
        if b % st.batch_split != 0 {
            notes.push(format!("batch_split {} does not divide --batch {b}: using batch_split 1", st.batch_split));
            st.batch_split = 1;
        }
    }
    if st.regions > 1 {
        notes.push(format!(
            "gdrf runs the two-pass patch step ({} regions); the reference renders whole images",
            st.regions
        ));
    }
    if cfg.camera.distribution != gdrf_core::PoseDistribution::Uniform {
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
    cfg.device = target.device.clone();
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

/// `warmup` untimed then `steps` timed training steps of gdrf. Timed steps run at step
/// indices where R1 is due (the counter is moved up to the next multiple of
/// `r1_interval`; a single stage has no fade-in, so nothing else depends on it).
fn bench_step_gdrf(cfg: TrainConfig, run_dir: &Path, warmup: usize, steps: usize) -> Result<serde_json::Value> {
    let threads = device::init_threads();
    let mut trainer = Trainer::new(cfg, run_dir)?;
    let t0 = Instant::now();
    trainer.prepare_data(&|| {})?;
    let res = trainer.cfg.stages[0].resolution;
    let n = trainer.dataset(res)?.len();
    eprintln!("procedural dataset: {n} images at {res}² ({:.1} s)", t0.elapsed().as_secs_f64());
    let report = |r: &gdrf_core::train::StepReport, what: &str| {
        let bad = if r.d_skipped || r.g_skipped { " (non-finite: update skipped)" } else { "" };
        eprintln!("gdrf {what} {}: {:.2} s{bad}", r.step, r.seconds);
    };
    for _ in 0..warmup {
        report(&trainer.step()?, "warm-up step");
    }
    let every = trainer.cfg.loss.r1_interval.max(1);
    let mut samples = Vec::with_capacity(steps);
    for _ in 0..steps {
        let s = trainer.progress.step;
        trainer.progress.step = (s + every - 1) / every * every;
        let r = trainer.step()?;
        report(&r, "step");
        samples.push(r.seconds);
    }
    let b = trainer.cfg.stages[0].batch_size as f64;
    let med = median(&samples);
    Ok(json!({
        "implementation": "gdrf (tch)",
        "threads": threads,
        "median_s": {"step": med},
        "samples_s": {"step": samples},
        "peak_rss_mb": peak_rss_mb(),
        "images_per_second": b / med,
    }))
}

/// The reference's flags for the same step (scripts/reference/bench_step.py).
fn step_reference_args(cfg: &TrainConfig, warmup: usize, steps: usize) -> Result<Vec<String>> {
    let st = &cfg.stages[0];
    let (g_lr, d_lr) = cfg.learning_rates(0);
    let (g, l, o, c) = (&cfg.generator, &cfg.loss, &cfg.optim, &cfg.camera);
    let list = |v: &[String]| v.join(",");
    let variant = serde_json::to_value(l.reg.variant)?.as_str().unwrap_or("release").to_string();
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

/// Where `gdrf-bench step` runs both implementations, and in which precision.
struct StepTarget {
    device: String,
    precision: Option<String>,
}

#[allow(clippy::too_many_arguments)]
fn bench_step(
    config: &Path,
    batch: Option<i64>,
    batch_split: Option<i64>,
    stage: usize,
    steps: usize,
    warmup: usize,
    no_reference: bool,
    target: &StepTarget,
    out_dir: &Path,
) -> Result<()> {
    if steps == 0 {
        bail!("--steps must be at least 1");
    }
    let tmp = TempDir::new("bench-step")?;
    let (cfg, notes) = step_config(config, stage, batch, batch_split, target, &tmp.0)?;
    let bf16 = cfg.precision == Precision::Bfloat16;
    for n in &notes {
        eprintln!("note: {n}");
    }
    let st = cfg.stages[0].clone();
    let (b, res, n) = (st.batch_size, st.resolution, st.num_steps);
    let stem = config.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "config".into());
    let r1 = if cfg.loss.r1_gamma == 0.0 { "R1 off".to_string() } else { "R1 due".to_string() };
    let title = format!(
        "Training step (D + G, Adam, EMA), {stem} stage {stage}: batch {b} (split {}), {res}², {n}+{n} samples, {r1}, {} {}",
        st.batch_split,
        target.device,
        if bf16 { "bfloat16" } else { "float32" }
    );
    eprintln!("{title}\nrunning gdrf ({warmup} warm-up + {steps} timed steps) …");
    let (g_lr, d_lr) = cfg.learning_rates(0);
    let settings = json!({
        "config": config.display().to_string(),
        "stage": stage,
        "resolution": res,
        "num_steps": n,
        "batch_size": b,
        "batch_split": st.batch_split,
        "regions": st.regions,
        "warmup_steps": warmup,
        "timed_steps": steps,
        "device": target.device,
        "precision": if bf16 { "bfloat16" } else { "float32" },
        "timed_steps_r1": "timed steps run at step indices where R1 is due (multiples of loss.r1_interval)",
        "real_images": "gdrf: a 64-image procedural dataset at the stage's resolution; reference: random images and poses",
        "g_lr": g_lr,
        "d_lr": d_lr,
        "generator": cfg.generator,
        "discriminator": cfg.discriminator,
        "loss": cfg.loss,
        "optim": cfg.optim,
        "ema": cfg.ema,
        "camera": cfg.camera,
        "notes": notes,
    });
    let mut ref_args = step_reference_args(&cfg, warmup, steps)?;
    ref_args.push(format!("--device={}", target.device));
    if bf16 {
        ref_args.push("--bf16".into());
    }
    let mut runs = vec![bench_step_gdrf(cfg, &tmp.0.join("run"), warmup, steps)?];
    if !no_reference {
        runs.push(run_reference("bench_step.py", &ref_args)?);
    }
    let num = |r: &serde_json::Value, k: &str| r[k].as_f64().unwrap_or(f64::NAN);
    let med = |r: &serde_json::Value| r["median_s"]["step"].as_f64().unwrap_or(f64::NAN);
    println!("{title}");
    println!("{:<20}{:>16}{:>12}{:>12}", "", "median s/step", "images/s", "peak MB");
    for r in &runs {
        println!(
            "{:<20}{:>16.3}{:>12.2}{:>12.0}",
            r["implementation"].as_str().unwrap_or("?"),
            med(r),
            num(r, "images_per_second"),
            num(r, "peak_rss_mb")
        );
    }
    if runs.len() == 2 {
        let (x, y) = (&runs[0], &runs[1]);
        println!(
            "{:<20}{:>15.2}×{:>11.2}×{:>11.2}×",
            "reference/gdrf",
            med(y) / med(x),
            num(y, "images_per_second") / num(x, "images_per_second"),
            num(y, "peak_rss_mb") / num(x, "peak_rss_mb")
        );
    }
    let machine = if target.device == "cpu" {
        format!("{} CPU threads", runs[0]["threads"])
    } else {
        format!("{}, {} CPU threads", target.device, runs[0]["threads"])
    };
    let doc = json!({
        "title": title,
        "machine": machine,
        "settings": settings,
        "phases": ["step"],
        "runs": runs,
    });
    let mut name = format!("step-{stem}-stage{stage}-b{b}");
    if target.device != "cpu" {
        name += &format!("-{}", target.device.replace(':', ""));
    }
    if bf16 {
        name += "-bf16";
    }
    write_report(out_dir, &name, &doc)
}

fn run() -> Result<()> {
    match Cli::parse().command {
        Bench::Step { config, batch, batch_split, stage, steps, warmup, no_reference, device, precision, out_dir } => {
            let target = StepTarget { device, precision };
            bench_step(&config, batch, batch_split, stage, steps, warmup, no_reference, &target, &out_dir)?;
        }
        Bench::Losses { batch, batch_split, resolution, steps, repeats, no_reference, out_dir } => {
            if batch_split < 1 || batch % batch_split != 0 {
                bail!("--batch-split {batch_split} must divide --batch {batch}");
            }
            if repeats == 0 {
                bail!("--repeats must be at least 1");
            }
            let title = format!(
                "G and D loss + backward, batch {batch} (split {batch_split}), {resolution}², {steps}+{steps} samples, regularisers on"
            );
            eprintln!("{title}\nrunning gdrf (after an untimed warm-up at 16²) …");
            bench_losses(batch_split, batch_split, 16, 8, 1)?;
            let mut runs = vec![bench_losses(batch, batch_split, resolution, steps, repeats)?];
            if !no_reference {
                let pairs = [
                    ("--batch", batch),
                    ("--batch-split", batch_split),
                    ("--resolution", resolution),
                    ("--steps", steps as i64),
                    ("--repeats", repeats as i64),
                ];
                let args: Vec<String> = pairs.iter().flat_map(|(k, v)| [k.to_string(), v.to_string()]).collect();
                runs.push(run_reference("bench_losses.py", &args)?);
            }
            println!("{title}");
            println!(
                "{:<14}{:>14}{:>14}{:>14}{:>14}{:>12}",
                "", "G forward s", "G backward s", "D forward s", "D backward s", "peak MB"
            );
            let phases = ["g_forward", "g_backward", "d_forward", "d_backward"];
            for r in &runs {
                print!("{:<14}", r["implementation"].as_str().unwrap_or("?"));
                for p in phases {
                    print!("{:>14.2}", r["median_s"][p].as_f64().unwrap_or(f64::NAN));
                }
                println!("{:>12.0}", r["peak_rss_mb"].as_f64().unwrap_or(f64::NAN));
            }
            if runs.len() == 2 {
                let total = |r: &serde_json::Value, a: &str, b: &str| {
                    r["median_s"][a].as_f64().unwrap() + r["median_s"][b].as_f64().unwrap()
                };
                for (name, a, b) in
                    [("G loss + backward", "g_forward", "g_backward"), ("D loss + backward", "d_forward", "d_backward")]
                {
                    let (x, y) = (total(&runs[0], a, b), total(&runs[1], a, b));
                    println!("{name}: gdrf {x:.2} s, reference {y:.2} s, reference/gdrf = {:.2}×", y / x);
                }
            }
            let doc = json!({"title": title, "machine": format!("{} CPU threads", runs[0]["threads"]), "phases": phases, "runs": runs});
            write_report(&out_dir, "losses", &doc)?;
        }
    }
    Ok(())
}
