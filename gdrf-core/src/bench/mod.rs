//! The benchmark commands (`gdrf-edit bench`: `render`, `gdrf-invert bench`: `invert`,
//! `gdrf-bench losses`, `step`, `shared-grid` and `allreduce`: `losses`, `step`,
//! `shared_grid`, `allreduce`) and what they share: medians, the
//! process's peak memory, running a PyTorch reference script (`scripts/reference/`) with
//! the project's Python, and writing their JSON.
//!
//! The commands themselves come with the `cli` feature: their options are the binaries'
//! flags (clap), and they draw progress bars (indicatif) as they run.
use crate::error::Context;
use crate::paths::{python, repo_root, write_atomic};
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Command, Stdio};

#[cfg(feature = "cli")]
pub mod allreduce;
#[cfg(feature = "cli")]
pub mod invert;
#[cfg(feature = "cli")]
pub mod losses;
#[cfg(feature = "cli")]
pub mod render;
#[cfg(feature = "cli")]
pub mod shared_grid;
#[cfg(feature = "cli")]
pub mod step;
#[cfg(feature = "cli")]
pub mod step_summary;

pub use crate::stats::median;

/// The process's peak resident memory so far in MB (Linux `VmHWM`; NaN elsewhere).
pub fn peak_rss_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| s.lines().find(|l| l.starts_with("VmHWM:")).map(|l| l.to_string()))
        .and_then(|l| l.split_whitespace().nth(1).and_then(|v| v.parse::<f64>().ok()))
        .map(|kb| kb / 1024.0)
        .unwrap_or(f64::NAN)
}

/// Runs `scripts/reference/<script>` with the project's Python and reads the JSON it
/// prints (its progress messages go to our stderr).
pub fn run_reference(script: &str, args: &[String]) -> Result<serde_json::Value> {
    eprintln!("running the PyTorch reference ({script}) …");
    let reference = |reason: String| Error::Subprocess { program: format!("the PyTorch reference {script}"), reason };
    let out = Command::new(python())
        .arg(repo_root().join("scripts/reference").join(script))
        .args(args)
        .stderr(Stdio::inherit())
        .output()
        .map_err(|e| reference(format!("could not start {} (run scripts/setup.sh): {e}", python().display())))?;
    if !out.status.success() {
        return Err(reference("failed (its messages are above)".into()));
    }
    serde_json::from_slice(&out.stdout).map_err(|e| reference(format!("printed no JSON: {e}")))
}

/// Starts `world` ranks of this program with arguments `args` and torchrun's variables
/// (rendezvous on a free loopback port), waits for them and returns rank 0's standard
/// output. Rank 0's messages reach ours; another rank's are shown only when it fails.
pub fn spawn_ranks(world: usize, args: &[std::ffi::OsString]) -> Result<Vec<u8>> {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map_err(|e| Error::Distributed(format!("no free port on loopback: {e}")))?
        .port();
    let exe = std::env::current_exe().map_err(|e| Error::Invalid(format!("cannot find this program: {e}")))?;
    let children: Vec<_> = (0..world)
        .map(|rank| {
            Command::new(&exe)
                .args(args)
                .env("RANK", rank.to_string())
                .env("WORLD_SIZE", world.to_string())
                .env("MASTER_ADDR", "127.0.0.1")
                .env("MASTER_PORT", port.to_string())
                .stdout(Stdio::piped())
                .stderr(if rank == 0 { Stdio::inherit() } else { Stdio::piped() })
                .spawn()
                .map_err(|e| Error::Invalid(format!("cannot start rank {rank}: {e}")))
        })
        .collect::<Result<_>>()?;
    let mut first = Vec::new();
    for (rank, child) in children.into_iter().enumerate() {
        let out = child.wait_with_output().map_err(|e| Error::Distributed(format!("rank {rank}: {e}")))?;
        if !out.status.success() {
            let said = String::from_utf8_lossy(&out.stderr);
            return Err(Error::Distributed(format!("rank {rank} failed ({}); {}", out.status, said.trim())));
        }
        if rank == 0 {
            first = out.stdout;
        }
    }
    Ok(first)
}

/// Writes `doc` to `path` atomically as pretty JSON, its keys in alphabetical order at
/// every level (it goes through a `serde_json::Value`), as the benchmark files have always
/// been written: a rerun diffs against the committed figures line by line.
pub fn write_json(path: &Path, doc: &impl Serialize) -> Result<()> {
    let text = serde_json::to_value(doc).and_then(|v| serde_json::to_string_pretty(&v))?;
    write_atomic(path, text.as_bytes())
}

/// A `gdrf-bench` document (losses.json, step-….json): gdrf's timings beside the PyTorch
/// reference's, per phase, drawn as bars ([`Timings::write`]).
#[derive(Serialize)]
pub struct Timings<S: Serialize> {
    pub title: String,
    /// CPU threads, and the device when it is not the CPU.
    pub machine: String,
    /// What was measured and how (the step benchmark's settings; none for the losses).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub settings: Option<S>,
    /// The keys of every run's `median_s`, in the order they are drawn.
    pub phases: Vec<&'static str>,
    /// gdrf's run, then the reference's (unless skipped).
    pub runs: Vec<Run>,
}

/// One implementation's timings: gdrf's, or what a reference script printed (same keys).
#[derive(Serialize, Deserialize)]
pub struct Run {
    pub implementation: String,
    pub threads: usize,
    /// Median seconds per phase.
    pub median_s: BTreeMap<String, f64>,
    /// Every timed repetition's seconds per phase.
    pub samples_s: BTreeMap<String, Vec<f64>>,
    pub peak_rss_mb: f64,
    /// Batch size over the median step (the step benchmark).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub images_per_second: Option<f64>,
    /// Whatever else the script reports (its torch version).
    #[serde(flatten)]
    pub other: serde_json::Map<String, serde_json::Value>,
}

impl Run {
    /// The median seconds of `phase` (NaN when it has none).
    pub fn median(&self, phase: &str) -> f64 {
        self.median_s.get(phase).copied().unwrap_or(f64::NAN)
    }
}

/// Runs a PyTorch reference script (as [`run_reference`]) that prints a [`Run`].
pub fn reference_run(script: &str, args: &[String]) -> Result<Run> {
    serde_json::from_value(run_reference(script, args)?).map_err(|e| Error::Subprocess {
        program: format!("the PyTorch reference {script}"),
        reason: format!("printed no timings: {e}"),
    })
}

impl<S: Serialize> Timings<S> {
    /// Writes `OUT_DIR/<name>.json` atomically and its bar chart `<name>.png`.
    pub fn write(&self, out_dir: &Path, name: &str) -> Result<()> {
        std::fs::create_dir_all(out_dir).with_context(|| format!("creating {}", out_dir.display()))?;
        let json_path = out_dir.join(format!("{name}.json"));
        write_json(&json_path, self)?;
        let png = out_dir.join(format!("{name}.png"));
        let bars = crate::plot::Bars {
            title: self.title.clone(),
            y_label: "median seconds".into(),
            groups: self.phases.iter().map(|p| p.to_string()).collect(),
            series: self
                .runs
                .iter()
                .map(|r| (r.implementation.clone(), self.phases.iter().map(|p| r.median(p)).collect()))
                .collect(),
        };
        crate::io::save_png(&png, &crate::plot::draw_bars(&bars, 820, 420)?)?;
        println!("wrote {} and {}", json_path.display(), png.display());
        Ok(())
    }
}
