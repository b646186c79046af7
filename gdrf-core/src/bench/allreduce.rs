//! `gdrf-bench allreduce`: the gradient all-reduce of data-parallel training against the
//! bucket size, through gdrf's c10d bridge ([`crate::dist`]) and through
//! `torch.distributed` (scripts/reference/bench_allreduce.py) on the same tensors: the
//! parameters of a training config's generator and discriminator, Gloo over loopback,
//! one thread a rank.
//!
//! The command starts `--world` copies of itself as the ranks (`--worker`, with torchrun's
//! variables), then the reference, and reads rank 0's timings from each.
use super::{median, run_reference, spawn_ranks, write_json};
use crate::dist::{Launch, ProcessGroup, Reduce};
use crate::plot::{draw_panels, Panel, Series};
use crate::train::TrainConfig;
use crate::{Error, Generator, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use tch::{nn, Device, Kind, Tensor};

/// The flags of `gdrf-bench allreduce`.
#[derive(clap::Args, Clone)]
pub struct Options {
    /// Training config (TOML) whose generator and discriminator give the tensors.
    #[arg(long, default_value = "configs/chairs-tiny.toml")]
    pub config: PathBuf,
    /// Ranks (processes on this machine).
    #[arg(long, default_value_t = 2)]
    pub world: usize,
    /// Bucket sizes in KiB (comma-separated).
    #[arg(long, value_delimiter = ',', default_value = "16,64,256,1024,4096,16384")]
    pub bucket_kib: Vec<usize>,
    /// Timed all-reduces per bucket size (the median is reported).
    #[arg(long, default_value_t = 30)]
    pub repeats: usize,
    /// Untimed all-reduces first, per bucket size.
    #[arg(long, default_value_t = 3)]
    pub warmup: usize,
    /// Skip the PyTorch reference.
    #[arg(long)]
    pub no_reference: bool,
    /// Folder for allreduce-<world>ranks.json and .png.
    #[arg(long, default_value = "bench")]
    pub out_dir: PathBuf,
    /// Run as one rank (set by the command itself for the processes it starts).
    #[arg(long, hide = true)]
    pub worker: bool,
}

/// One implementation's medians, in the order of `bucket_kib`.
#[derive(Serialize, Deserialize)]
pub struct Timings {
    pub median_ms: Vec<f64>,
}

#[derive(Serialize)]
pub struct Report {
    pub config: String,
    pub world: usize,
    pub tensors: usize,
    pub bytes: usize,
    pub bucket_kib: Vec<usize>,
    pub repeats: usize,
    pub gdrf: Timings,
    pub torch: Option<Timings>,
    /// gdrf's median over torch's, per bucket size.
    pub ratio: Option<Vec<f64>>,
}

/// The float32 parameters of `cfg`'s generator and discriminator (the step's gradients).
fn shapes(cfg: &TrainConfig) -> Result<Vec<Vec<i64>>> {
    let vs = nn::VarStore::new(Device::Cpu);
    Generator::new(&(vs.root() / "generator"), &cfg.generator)?;
    crate::disc::build(&(vs.root() / "discriminator"), &cfg.discriminator)?;
    let mut vars: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
    vars.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(vars.into_iter().map(|(_, t)| t.size()).collect())
}

/// One rank: join, then time `repeats` all-reduces per bucket size (a barrier before
/// each); rank 0 prints its medians as JSON.
fn worker(a: &Options, shapes: &[Vec<i64>]) -> Result<()> {
    tch::set_num_threads(1);
    let pg = ProcessGroup::join(&Launch::from_env()?, Duration::from_secs(60))?;
    let tensors: Vec<Tensor> = shapes.iter().map(|s| Tensor::randn(s.as_slice(), (Kind::Float, Device::Cpu))).collect();
    let mut medians = Vec::new();
    for &kib in &a.bucket_kib {
        let mut times = Vec::new();
        for i in 0..a.warmup + a.repeats {
            pg.barrier()?;
            let start = Instant::now();
            pg.all_reduce(&tensors, Reduce::Average, kib * 1024)?;
            if i >= a.warmup {
                times.push(start.elapsed().as_secs_f64() * 1e3);
            }
        }
        medians.push(median(&times));
    }
    if pg.rank() == 0 {
        println!("{}", serde_json::to_string(&Timings { median_ms: medians })?);
    }
    Ok(())
}

/// Starts the ranks and reads rank 0's timings.
fn ranks(a: &Options) -> Result<Timings> {
    let kib: Vec<String> = a.bucket_kib.iter().map(usize::to_string).collect();
    let mut args: Vec<std::ffi::OsString> = vec!["allreduce".into(), "--worker".into(), "--config".into()];
    args.push(a.config.clone().into());
    for (flag, value) in
        [("--bucket-kib", kib.join(",")), ("--repeats", a.repeats.to_string()), ("--warmup", a.warmup.to_string())]
    {
        args.extend([flag.into(), value.into()]);
    }
    let out = spawn_ranks(a.world, &args)?;
    serde_json::from_slice(&out).map_err(|e| Error::Distributed(format!("rank 0 printed no timings: {e}")))
}

/// Runs the benchmark (or, with `--worker`, one rank of it: then no report).
pub fn run(a: &Options) -> Result<Option<Report>> {
    let cfg = TrainConfig::load(&a.config)?;
    let shapes = shapes(&cfg)?;
    if a.worker {
        return worker(a, &shapes).map(|()| None);
    }
    if a.world < 2 || a.bucket_kib.is_empty() || a.bucket_kib.contains(&0) || a.repeats == 0 {
        return Err(Error::Invalid("--world must be at least 2, --bucket-kib positive sizes, --repeats ≥ 1".into()));
    }
    let bytes: usize = shapes.iter().map(|s| s.iter().product::<i64>() as usize * 4).sum();
    eprintln!("{} tensors, {:.2} MB, {} ranks, Gloo over loopback …", shapes.len(), bytes as f64 / 1e6, a.world);
    let gdrf = ranks(a)?;
    let torch = if a.no_reference {
        None
    } else {
        let shape_arg = serde_json::to_string(&shapes)?;
        let kib: Vec<String> = a.bucket_kib.iter().map(usize::to_string).collect();
        let v = run_reference(
            "bench_allreduce.py",
            &[
                "--world".into(),
                a.world.to_string(),
                "--shapes".into(),
                shape_arg,
                "--bucket-kib".into(),
                kib.join(","),
                "--repeats".into(),
                a.repeats.to_string(),
                "--warmup".into(),
                a.warmup.to_string(),
            ],
        )?;
        Some(serde_json::from_value::<Timings>(v)?)
    };
    let ratio = torch.as_ref().map(|t| gdrf.median_ms.iter().zip(&t.median_ms).map(|(g, t)| g / t).collect());
    let report = Report {
        config: crate::paths::shown(&a.config),
        world: a.world,
        tensors: shapes.len(),
        bytes,
        bucket_kib: a.bucket_kib.clone(),
        repeats: a.repeats,
        gdrf,
        torch,
        ratio,
    };
    for (i, kib) in report.bucket_kib.iter().enumerate() {
        let t =
            report.torch.as_ref().map_or(String::new(), |t| format!(", torch.distributed {:.2} ms", t.median_ms[i]));
        println!("bucket {kib:>6} KiB: gdrf {:.2} ms{t}", report.gdrf.median_ms[i]);
    }
    report.write(&a.out_dir)?;
    Ok(Some(report))
}

impl Report {
    fn write(&self, out_dir: &Path) -> Result<()> {
        std::fs::create_dir_all(out_dir).map_err(|e| Error::Io { path: out_dir.to_path_buf(), err: e })?;
        let stem = out_dir.join(format!("allreduce-{}ranks", self.world));
        let points =
            |t: &Timings| self.bucket_kib.iter().zip(&t.median_ms).map(|(&k, &m)| ((k as f64).log2(), m)).collect();
        let mut series = vec![Series { name: "gdrf (c10d bridge)".into(), points: points(&self.gdrf) }];
        if let Some(t) = &self.torch {
            series.push(Series { name: "torch.distributed".into(), points: points(t) });
        }
        let title =
            format!("all-reduce of {:.1} MB, {} ranks: ms vs log2 bucket KiB", self.bytes as f64 / 1e6, self.world);
        let panel = Panel { title, series, log_y: false, marks: vec![] };
        crate::io::save_png(&PathBuf::from(format!("{}.png", stem.display())), &draw_panels(&[panel], 1, 520, 300)?)?;
        write_json(&PathBuf::from(format!("{}.json", stem.display())), self)?;
        println!("wrote {}.json and .png", stem.display());
        Ok(())
    }
}
