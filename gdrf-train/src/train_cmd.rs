//! `gdrf-train --config FILE` / `--resume RUN_DIR` / `--print-config FILE`: argument
//! handling, progress display and signals around [`gdrf_core::train::Trainer::run`].
use anyhow::{bail, Context, Result};
use clap::Args;
use gdrf_core::progress;
use gdrf_core::train::config::{cpu_has_bf16, Precision};
use gdrf_core::train::{run, samples, Progress, RunLimits, StepReport, Stopped, TrainConfig, Trainer};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

#[derive(Args)]
pub struct TrainArgs {
    /// Start a training run from this config (TOML; see configs/). With --resume: continue
    /// that run under this config instead of its own (a longer or changed schedule; the
    /// networks and camera must match).
    #[arg(long, value_name = "TOML", conflicts_with = "print_config")]
    config: Option<PathBuf>,
    /// Continue the run in RUN_DIR from its newest checkpoint, exactly where it stopped
    /// (with the config saved in the checkpoint, unless --config is given).
    #[arg(long, value_name = "RUN_DIR", conflicts_with = "print_config")]
    resume: Option<PathBuf>,
    /// Print the resolved config (every default filled in) and exit.
    #[arg(long, value_name = "TOML")]
    print_config: Option<PathBuf>,
    /// Run directory of a new run (default: runs/<config file name>).
    #[arg(long, value_name = "DIR", requires = "config", conflicts_with = "resume")]
    run_dir: Option<PathBuf>,
    /// Start over in a run directory that already holds a run (its checkpoints, metrics
    /// and samples are removed first).
    #[arg(long, requires = "config", conflicts_with = "resume")]
    force: bool,
    /// Stop this session after N steps (with a checkpoint); `--resume` continues.
    #[arg(long, value_name = "N")]
    steps: Option<i64>,
    /// Stop this session after about M minutes (checked between steps, with a checkpoint).
    #[arg(long, value_name = "M")]
    minutes: Option<f64>,
    /// auto, cpu, cuda or cuda:N (overrides the config's `device`).
    #[arg(long)]
    device: Option<String>,
    /// libtorch threads (overrides the config's `threads`; 0 = all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Start the new run's generator (live and EMA) from this generator file, e.g. a shipped
    /// model's generator.safetensors, instead of random weights; the discriminator starts
    /// fresh. Sets the config's `init_generator`; the architectures must match.
    #[arg(long, value_name = "FILE", requires = "config", conflicts_with = "resume")]
    init_generator: Option<PathBuf>,
    /// No progress bars, in training (one line per logged step instead) and in every
    /// subcommand (`eval --quiet`, `dataset synth --quiet`), e.g. for logs of background runs.
    #[arg(long, global = true)]
    pub quiet: bool,
    /// Data-parallel training: start N worker processes on this machine, ranks of one run
    /// that split each stage's global batch equally (on CUDA each takes cuda:LOCAL_RANK; on
    /// the CPU the cores are divided among them). Workers also start from torchrun's
    /// variables (RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR, MASTER_PORT) when these are set.
    #[arg(long, value_name = "N", default_value_t = 1)]
    nproc: usize,
    /// Machines of a multi-machine run; each runs the same command with its --node-rank.
    #[arg(long, value_name = "M", default_value_t = 1)]
    nnodes: usize,
    /// This machine's index among --nnodes (0 serves the rendezvous).
    #[arg(long, value_name = "I", default_value_t = 0)]
    node_rank: usize,
    /// Address of machine 0, where rank 0 serves the rendezvous.
    #[arg(long, value_name = "HOST", default_value = "127.0.0.1")]
    master_addr: String,
    /// Port of the rendezvous on --master-addr.
    #[arg(long, value_name = "PORT", default_value_t = gdrf_core::dist::DEFAULT_PORT)]
    master_port: u16,
    /// Seconds a rank waits for the others (the rendezvous, each collective, rank 0's
    /// evaluations) before it fails with an error naming the rank.
    #[arg(long, value_name = "SECONDS", default_value_t = 1800)]
    dist_timeout: u64,
}

/// Starts this machine's ranks of a data-parallel run (this same command, with torchrun's
/// variables) and waits for them. Once one fails, the others get --dist-timeout (and ten
/// seconds to write their error) to fail too, as they do when a peer is gone or silent;
/// one still running after that (stopped, or hung outside a collective) is killed. The
/// error names the rank that failed first, and how.
fn launch(a: &TrainArgs) -> Result<()> {
    if a.nproc == 0 || a.nnodes == 0 || a.node_rank >= a.nnodes {
        bail!("--nproc and --nnodes must be at least 1, and --node-rank less than --nnodes");
    }
    let exe = std::env::current_exe().context("finding this program")?;
    let world = a.nproc * a.nnodes;
    let mut ranks = Vec::new();
    for local in 0..a.nproc {
        let rank = a.node_rank * a.nproc + local;
        let child = std::process::Command::new(&exe)
            .args(std::env::args_os().skip(1))
            .env("RANK", rank.to_string())
            .env("WORLD_SIZE", world.to_string())
            .env("LOCAL_RANK", local.to_string())
            .env("LOCAL_WORLD_SIZE", a.nproc.to_string())
            .env("MASTER_ADDR", &a.master_addr)
            .env("MASTER_PORT", a.master_port.to_string())
            .spawn()
            .with_context(|| format!("starting rank {rank}"))?;
        ranks.push((rank, child, None));
    }
    let grace = std::time::Duration::from_secs(a.dist_timeout.saturating_add(10));
    let mut first_failure: Option<std::time::Instant> = None;
    let mut failed = Vec::new();
    let mut killed = Vec::new();
    while ranks.iter().any(|r| r.2.is_none()) {
        for (rank, child, status) in ranks.iter_mut().filter(|r| r.2.is_none()) {
            if let Some(st) = child.try_wait().with_context(|| format!("waiting for rank {rank}"))? {
                *status = Some(st);
                if !st.success() {
                    first_failure.get_or_insert_with(std::time::Instant::now);
                    failed.push((*rank, st));
                }
            }
        }
        if first_failure.is_some_and(|t| t.elapsed() > grace) {
            for (rank, child, status) in ranks.iter_mut().filter(|r| r.2.is_none()) {
                let _ = child.kill();
                *status = Some(child.wait()?);
                killed.push(*rank);
            }
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    // Of the ranks seen failing in the same poll, one ended by a signal is the cause.
    failed.sort_by_key(|(_, st)| st.code().is_some());
    let stopped = if killed.is_empty() {
        String::new()
    } else {
        format!("; still running {:.0?} later, rank(s) {killed:?} were killed", grace)
    };
    match failed.first() {
        None => Ok(()),
        Some((_, status)) if status.code() == Some(130) && failed.iter().all(|(_, s)| s.code() == Some(130)) => {
            std::process::exit(130)
        }
        Some((rank, status)) if status.code().is_none() => {
            bail!("rank {rank} of {world} was killed ({status}); the other ranks then stopped{stopped}")
        }
        Some((rank, status)) => bail!("rank {rank} of {world} failed ({status}); its error is above{stopped}"),
    }
}

impl TrainArgs {
    pub fn any(&self) -> bool {
        self.config.is_some() || self.resume.is_some() || self.print_config.is_some()
    }
}

fn default_run_dir(config: &Path) -> PathBuf {
    let stem = config.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "run".into());
    PathBuf::from("runs").join(stem)
}

pub fn train(a: TrainArgs) -> Result<()> {
    if let Some(path) = &a.print_config {
        let cfg = TrainConfig::load(path)?;
        print!("{}", cfg.to_toml()?);
        return Ok(());
    }
    // A rank of a data-parallel run when torchrun's variables are set; the launcher of
    // this machine's ranks when --nproc or --nnodes asks for more than one process.
    let rank = match std::env::var_os("WORLD_SIZE") {
        Some(_) => Some(gdrf_core::dist::Launch::from_env()?),
        None if a.nproc > 1 || a.nnodes > 1 => return launch(&a),
        None => None,
    };
    let writer = rank.as_ref().is_none_or(|l| l.rank == 0);
    if a.steps.is_some_and(|n| n < 1) || a.minutes.is_some_and(|m| m.is_nan() || m <= 0.0) {
        bail!("--steps and --minutes must be positive");
    }
    let (_lock, mut trainer) = open(&a, rank.as_ref())?;
    let threads = gdrf_core::data::thread_count(trainer.cfg().threads);
    tch::set_num_threads(threads as i32);
    let stop = stop_on_signals()?;
    prepare_data(&trainer, rank.as_ref(), writer)?;
    announce(&mut trainer, threads, writer)?;
    let limits = RunLimits { steps: a.steps, seconds: a.minutes.map(|m| m * 60.0) };
    if !writer {
        // The other ranks print only errors.
        if trainer.run(limits, &stop, |_, _| {})? == Stopped::Interrupted {
            std::process::exit(130);
        }
        return Ok(());
    }
    let stopped = run_with_bar(&mut trainer, &a, limits, &stop)?;
    summarise(&trainer, stopped)?;
    if stopped == Stopped::Interrupted {
        std::process::exit(130);
    }
    Ok(())
}

/// The session's trainer, from the flags: a new run (`--config`), the run of `--resume`
/// (under `--config` where given), with `--device` and `--threads`, joined to the ranks of
/// a data-parallel run; with the run folder's lock, held while it trains.
fn open(a: &TrainArgs, rank: Option<&gdrf_core::dist::Launch>) -> Result<(Option<run::RunLock>, Trainer)> {
    // On CUDA each rank of a machine takes its own GPU.
    let device = |d: &str| match rank {
        Some(l) if d == "cuda" => format!("cuda:{}", l.local_rank),
        _ => d.to_string(),
    };
    let load = |path: &Path| -> Result<TrainConfig> {
        let mut cfg = TrainConfig::load(path)?;
        if let Some(d) = &a.device {
            cfg.device = d.clone();
        }
        cfg.device = device(&cfg.device);
        if let Some(t) = a.threads {
            cfg.threads = t;
        }
        if let Some(g) = &a.init_generator {
            cfg.init_generator =
                Some(std::path::absolute(g).with_context(|| format!("--init-generator {}", g.display()))?);
        }
        cfg.validate()?;
        Ok(cfg)
    };
    // The config is read first: a bad one leaves no run directory behind.
    let config = a.config.as_deref().map(load).transpose()?;
    let (run_dir, opening) = match (&a.config, &a.resume) {
        (_, Some(dir)) if !dir.is_dir() => {
            bail!("--resume {}: no such folder (expected a gdrf-train run directory)", dir.display())
        }
        (_, Some(dir)) => (dir.clone(), run::Opening::Resume),
        (Some(path), None) => {
            (a.run_dir.clone().unwrap_or_else(|| default_run_dir(path)), run::Opening::New { force: a.force })
        }
        (None, None) => bail!("pass --config FILE or --resume RUN_DIR"),
    };
    let group = rank
        .map(|l| gdrf_core::dist::ProcessGroup::join(l, std::time::Duration::from_secs(a.dist_timeout)))
        .transpose()?;
    let (lock, mut trainer) = run::take(&run_dir, opening, group.as_ref(), || -> Result<Trainer> {
        Ok(match (config, &a.config, &a.resume) {
            (Some(cfg), Some(path), Some(dir)) => Trainer::resume_with(dir, cfg)
                .with_context(|| format!("resuming {} with {}", dir.display(), path.display()))?,
            (Some(cfg), _, None) => Trainer::new(cfg, &run_dir)?,
            (None, _, Some(dir)) => {
                let d = a.device.as_deref().map(device);
                let mut t =
                    Trainer::resume(dir, d.as_deref()).with_context(|| format!("resuming {}", dir.display()))?;
                if let Some(n) = a.threads {
                    t.set_threads(n);
                }
                t
            }
            _ => bail!("pass --config FILE or --resume RUN_DIR"),
        })
    })?;
    for (path, why) in trainer.skipped_checkpoints() {
        eprintln!("warning: passed over {}, which is damaged: {why}", path.display());
    }
    if let Some(group) = group {
        // The machine's cores divided among its ranks, unless --threads says otherwise.
        if a.threads.is_none() {
            let here: usize = std::env::var("LOCAL_WORLD_SIZE").ok().and_then(|v| v.parse().ok()).unwrap_or(1);
            trainer.set_threads((gdrf_core::data::thread_count(0) / here.max(1)).max(1));
        }
        trainer.join_group(group)?;
    }
    Ok((lock, trainer))
}

/// A flag Ctrl-C and SIGTERM raise: the session finishes its step and writes a checkpoint.
/// A second one exits at once.
fn stop_on_signals() -> Result<Arc<AtomicBool>> {
    let stop = Arc::new(AtomicBool::new(false));
    let raised = stop.clone();
    ctrlc::set_handler(move || {
        if raised.swap(true, Ordering::SeqCst) {
            eprintln!("\nsecond interrupt: exiting now, without a checkpoint of the step in progress");
            std::process::exit(130);
        }
        eprintln!("\ninterrupt: finishing the current step, then writing a checkpoint (Ctrl-C again to exit at once)");
    })
    .context("installing the Ctrl-C/SIGTERM handler")?;
    Ok(stop)
}

/// Generates a missing procedural dataset. The first rank of each machine generates it
/// while the others wait, then they find it finished: two generators rewriting the same
/// PNGs let a rank read an image another was still writing (seen as "empty file").
fn prepare_data(trainer: &Trainer, rank: Option<&gdrf_core::dist::Launch>, writer: bool) -> Result<()> {
    let gen_bar = progress::bar(0, "images", !writer);
    let first_here = rank.is_none_or(|l| l.local_rank == 0);
    let prepared = if first_here {
        trainer.prepare_data(&|e| progress::follow(&gen_bar, e))?
    } else {
        gdrf_core::data::Prepared::Existing
    };
    trainer.barrier()?;
    if !first_here {
        trainer.prepare_data(&|_| {})?;
    }
    gen_bar.finish_and_clear();
    if writer && prepared == gdrf_core::data::Prepared::Generated {
        println!("generated the procedural dataset in {}", trainer.cfg().data.path.display());
    }
    Ok(())
}

/// Loads the training images (every rank, before the first step) and, on the rank that
/// writes, says what the session trains: the run, where it stands, the device, threads and
/// precision, the networks' sizes and the training images.
fn announce(trainer: &mut Trainer, threads: usize, writer: bool) -> Result<()> {
    let cfg = trainer.cfg().clone();
    let stage = cfg.stage(trainer.progress().step);
    let (g_params, d_all, d_used) = trainer.parameter_counts(stage.judged_size());
    let n_images = trainer.dataset(stage.resolution)?.len();
    if !writer {
        return Ok(());
    }
    let from = trainer.progress().step;
    let (_, world) = trainer.rank_of();
    let ranks = if world > 1 { format!(", {world} ranks") } else { String::new() };
    let precision = cfg.precision.on(trainer.device());
    println!(
        "{} run {} at step {from}/{} on {:?} with {threads} threads{ranks}, {}",
        if from == 0 { "starting" } else { "resuming" },
        trainer.run_dir().display(),
        cfg.schedule.total_steps,
        trainer.device(),
        serde_json::to_value(precision)?.as_str().unwrap_or("?")
    );
    if precision == Precision::Bfloat16 && trainer.device() == tch::Device::Cpu && !cpu_has_bf16() {
        eprintln!(
            "warning: precision = \"bfloat16\" on a CPU without bfloat16 instructions (AVX512-BF16, AMX): \
             libtorch multiplies bfloat16 matrices in scalar code there, many times slower than float32; \
             set precision = \"auto\" or \"float32\""
        );
    }
    let judged = match &stage.patch {
        Some(p) => format!("{}² patches of {}² images", p.size, stage.resolution),
        None => format!("{}²", stage.resolution),
    };
    println!(
        "generator {g_params} parameters, discriminator {d_all} ({d_used} used at {judged}); {n_images} training images from {}",
        cfg.data.path.display(),
    );
    Ok(())
}

/// Trains under a progress bar (or, `--quiet`, one line per logged step).
fn run_with_bar(trainer: &mut Trainer, a: &TrainArgs, limits: RunLimits, stop: &AtomicBool) -> Result<Stopped> {
    let log_interval = trainer.cfg().schedule.log_interval;
    let bar = progress::bar(trainer.cfg().schedule.total_steps as u64, "steps", a.quiet);
    bar.set_position(trainer.progress().step as u64);
    // A moving average of the seconds a step, not of each step's rate: with the coverage
    // term on every 4th step, averaging rates showed 340 img/s for a GPU run that did 74.
    let mut step_seconds = None::<f64>;
    let stopped = trainer.run(limits, stop, |r, p| {
        let secs = *step_seconds.insert(step_seconds.map_or(r.seconds, |old| 0.9 * old + 0.1 * r.seconds));
        let msg = step_message(r, p, secs);
        bar.set_prefix(format!("stage {}", r.stage));
        bar.set_position(p.step as u64);
        if let Some(to) = r.rolled_back_to {
            // Above the bar, and in logs too (a hidden bar's println writes nothing).
            bar.suspend(|| {
                eprintln!(
                    "step {}: non-finite steps in a row; rolled back to step {to} with lr × {}",
                    r.step, p.lr_scale
                )
            });
        }
        if a.quiet && r.step % log_interval == 0 {
            println!("step {} {msg}", r.step);
        }
        bar.set_message(msg);
    })?;
    bar.finish_and_clear();
    Ok(stopped)
}

/// A step's line: resolution, fade-in, speed (`secs` a step, averaged), the players'
/// main terms, and the skips and rollbacks once there are any.
fn step_message(r: &StepReport, p: &Progress, secs: f64) -> String {
    let ips = r.batch_size as f64 / secs.max(1e-9);
    let term = |k: &str| r.g_terms.iter().chain(&r.d_terms).find(|t| t.0 == k).map_or(f64::NAN, |t| t.1);
    let g = if r.lr_g == 0.0 {
        "G off (g_lr 0: the discriminator trains alone)".to_string()
    } else {
        format!("G adv {:.3} pose {:.3} reg {:.3}", term("g_adv"), term("g_pose"), term("reg_normal"))
    };
    format!(
        "{}² α {:.2} | {ips:.1} img/s | D {:.3} (real {:.3} fake {:.3}) | {g}{}",
        r.resolution,
        r.alpha,
        r.d_total,
        term("d_real"),
        term("d_fake"),
        if p.skipped_steps > 0 {
            format!(" | skipped {} rollbacks {}", p.skipped_steps, p.rollbacks)
        } else {
            String::new()
        }
    )
}

/// How the session ended, and where its checkpoint, generator, metrics and previews are.
fn summarise(trainer: &Trainer, stopped: Stopped) -> Result<()> {
    let p = trainer.progress();
    let (latest, _) = run::latest_checkpoint(trainer.run_dir())?;
    let dir = trainer.run_dir().display();
    match stopped {
        Stopped::Finished => println!("finished: {} steps", p.step),
        Stopped::Limit => {
            println!("stopped at step {} (session limit); continue with `gdrf-train --resume {dir}`", p.step)
        }
        Stopped::Interrupted => {
            println!("interrupted at step {}; checkpoint written; continue with `gdrf-train --resume {dir}`", p.step)
        }
    }
    println!(
        "checkpoint step {latest} in {dir}/{}/, EMA generator {dir}/{}, metrics {dir}/{} ({} steps skipped, {} rollbacks, {:.0} s training in all)",
        run::CHECKPOINTS,
        run::GENERATOR,
        run::METRICS,
        p.skipped_steps,
        p.rollbacks,
        p.train_seconds
    );
    if trainer.cfg().schedule.sample_interval > 0 {
        let shown: Vec<String> =
            samples::latest_previews(trainer.run_dir()).iter().map(|p| p.display().to_string()).collect();
        println!("previews: {}", shown.join(", "));
    }
    Ok(())
}
