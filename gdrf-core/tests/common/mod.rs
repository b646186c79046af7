//! Helpers shared by the integration tests: the project's Python, reference runs,
//! and error reports.
#![allow(dead_code)]
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use tch::Tensor;

pub use gdrf_core::paths::repo_root;

/// The project's Python (set up by scripts/setup.sh). Panics with instructions when it is
/// missing or lacks torch: cross-checks never skip silently.
pub fn python() -> PathBuf {
    let py = gdrf_core::paths::python();
    let ok = Command::new(&py)
        .args(["-c", "import torch, safetensors, numpy; assert torch.__version__.startswith('2.11.0')"])
        .status()
        .map(|s| s.success())
        .unwrap_or(false);
    assert!(
        ok,
        "the PyTorch reference needs {} with torch 2.11.0, safetensors and numpy: run scripts/setup.sh",
        py.display()
    );
    py
}

/// Runs a script of scripts/ with the project's Python; panics with its output on failure.
pub fn run_python(script: &str, args: &[&str]) {
    let out = Command::new(python())
        .arg(repo_root().join("scripts").join(script))
        .args(args)
        .output()
        .expect("failed to start python");
    assert!(
        out.status.success(),
        "{script} {args:?} failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

#[allow(unused_imports)]
pub use gdrf_core::paths::TempDir;

pub fn read_tensors(path: &Path) -> HashMap<String, Tensor> {
    Tensor::read_safetensors(path).unwrap().into_iter().collect()
}

/// max |a − b| / max |b|: the error relative to the reference tensor's scale.
pub fn rel_err(a: &Tensor, b: &Tensor) -> f64 {
    assert_eq!(a.size(), b.size(), "shape mismatch");
    let a = a.detach().to_kind(tch::Kind::Double);
    let b = b.detach().to_kind(tch::Kind::Double);
    let num = f64::try_from((&a - &b).abs().max()).unwrap();
    let den = f64::try_from(b.abs().max()).unwrap();
    assert!(num.is_finite(), "non-finite difference");
    if den == 0.0 {
        num
    } else {
        num / den
    }
}

/// Collects the worst relative error per component and checks them against a tolerance
/// (or a row's own bound, [`Report::bounded`]).
pub struct Report {
    pub title: String,
    pub tol: f64,
    pub rows: Vec<(String, f64)>,
    /// Rows held to their own bound instead of `tol`: (name, error, bound).
    pub bounded_rows: Vec<(String, f64, f64)>,
}

impl Report {
    pub fn new(title: &str, tol: f64) -> Self {
        Self { title: title.into(), tol, rows: Vec::new(), bounded_rows: Vec::new() }
    }
    /// A row whose error `e` must stay within `bound` rather than the report's tolerance.
    pub fn bounded(&mut self, name: &str, e: f64, bound: f64) {
        self.bounded_rows.push((name.to_string(), e, bound));
    }
    pub fn check(&mut self, name: &str, got: &Tensor, want: &Tensor) {
        let e = rel_err(got, want);
        self.rows.push((name.to_string(), e));
    }
    /// Records the worst error of several tensors under one component name.
    pub fn check_all(&mut self, name: &str, pairs: &[(Tensor, Tensor)]) {
        let e = pairs.iter().map(|(g, w)| rel_err(g, w)).fold(0.0, f64::max);
        self.rows.push((name.to_string(), e));
    }
    pub fn finish(self) {
        println!("{} (tolerance {:e}, max |Δ| / max |reference|):", self.title, self.tol);
        let rows = self
            .rows
            .iter()
            .map(|(n, e)| (n, *e, self.tol))
            .chain(self.bounded_rows.iter().map(|(n, e, b)| (n, *e, *b)));
        let mut bad = Vec::new();
        for (n, e, bound) in rows {
            let within = if bound == self.tol { String::new() } else { format!(" (bound {bound:.3e})") };
            let fail = e.is_nan() || e > bound;
            println!("  {n:<36} {e:.3e}{within}{}", if fail { "   FAIL" } else { "" });
            if fail {
                bad.push((n.clone(), e, bound));
            }
        }
        assert!(bad.is_empty(), "{}: components above their bound: {bad:?}", self.title);
    }
}

/// A training config of a tiny model (widths 8 and 4) for tests that run steps in
/// seconds: `top` goes before the tables (seed, device, precision…), `schedule` is the
/// body of `[schedule]`, `rest` ends the file (`[samples]`, `[[stages]]`, `[data]`…).
pub fn tiny_training_toml(top: &str, schedule: &str, rest: &str) -> String {
    format!(
        r#"
device = "cpu"
{top}

[generator]
latent_dim = 8
hidden_dim = 8
mapping_hidden_dim = 8

[discriminator]
channels = [4, 4, 4, 4, 4, 4, 4, 4, 4]

[schedule]
{schedule}
{rest}
"#
    )
}

/// Element-wise check |got − want| ≤ atol + rtol·|want| (in float64); panics naming the
/// worst element, its two values and how many elements fail. Returns the worst excess ratio
/// |Δ| / (atol + rtol·|want|) for reporting.
pub fn assert_close(name: &str, got: &Tensor, want: &Tensor, atol: f64, rtol: f64) -> f64 {
    assert_eq!(got.size(), want.size(), "{name}: shape {:?} vs reference {:?}", got.size(), want.size());
    let g = got.detach().to_device(tch::Device::Cpu).to_kind(tch::Kind::Double).flatten(0, -1);
    let w = want.detach().to_device(tch::Device::Cpu).to_kind(tch::Kind::Double).flatten(0, -1);
    assert!(bool::try_from(g.isfinite().all()).unwrap(), "{name}: non-finite values");
    let ratio = (&g - &w).abs() / (w.abs() * rtol + atol);
    let worst = i64::try_from(ratio.argmax(None, false)).unwrap();
    let r = f64::try_from(ratio.get(worst)).unwrap();
    let fails = i64::try_from(ratio.gt(1.0).sum(tch::Kind::Int64)).unwrap();
    assert!(
        fails == 0,
        "{name}: {fails} of {} elements exceed atol {atol:e} + rtol {rtol:e}; worst at {worst}: got {}, want {}",
        g.numel(),
        f64::try_from(g.get(worst)).unwrap(),
        f64::try_from(w.get(worst)).unwrap()
    );
    r
}

/// A tiny training config (8² images, 8 synthetic chairs, one thread, a metrics line every
/// step, a checkpoint only at the end, no previews) written to DIR/tiny.toml.
pub fn tiny_run_config(dir: &Path, total_steps: i64) -> PathBuf {
    let text = tiny_training_toml(
        "seed = 1\nthreads = 1",
        &format!("total_steps = {total_steps}\nlog_interval = 1\ncheckpoint_interval = 1000\nsample_interval = 0"),
        r#"
[[stages]]
from_step = 0
resolution = 8
num_steps = 4
batch_size = 2

[data]
path = "data"

[data.synth]
count = 8
resolution = 16
supersample = 1
shadows = false
"#,
    );
    let path = dir.join("tiny.toml");
    std::fs::write(&path, text).unwrap();
    path
}

/// The text of [`tiny_run_config`] at batch 4, which splits into two even shares (the
/// data-parallel tests' two ranks).
pub fn tiny_two_rank_config(dir: &Path, total_steps: i64) -> String {
    let text = std::fs::read_to_string(tiny_run_config(dir, total_steps)).unwrap();
    assert!(text.contains("batch_size = 2\n"), "{text}");
    text.replace("batch_size = 2\n", "batch_size = 4\n")
}

/// Starts test `test` of this test binary again, as rank `rank` of `world` (torchrun's
/// variables, rendezvous on loopback `port`), with `env` set too; its output piped.
pub fn spawn_rank(
    test: &str,
    env: (&str, &std::ffi::OsStr),
    rank: usize,
    world: usize,
    port: u16,
) -> std::process::Child {
    Command::new(std::env::current_exe().unwrap())
        .args(["--exact", test, "--nocapture", "--test-threads", "1"])
        .env(env.0, env.1)
        .env("RANK", rank.to_string())
        .env("WORLD_SIZE", world.to_string())
        .env("MASTER_ADDR", "127.0.0.1")
        .env("MASTER_PORT", port.to_string())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap()
}

/// Waits for `child` at most `limit`; kills it and panics past that (no test may hang).
/// Returns whether it succeeded and what it printed.
pub fn finish(mut child: std::process::Child, limit: std::time::Duration, what: &str) -> (bool, String) {
    let start = std::time::Instant::now();
    while child.try_wait().unwrap().is_none() {
        if start.elapsed() > limit {
            let _ = child.kill();
            let out = child.wait_with_output().unwrap();
            panic!("{what} still running after {limit:?}:\n{}", String::from_utf8_lossy(&out.stdout));
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    let out = child.wait_with_output().unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    (out.status.success(), text)
}

/// The checkpoint files of a run (`step-N.safetensors`, no temporaries), oldest first.
pub fn checkpoint_names(run: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(run.join("checkpoints"))
        .map(|d| d.filter_map(|e| e.ok()).map(|e| e.file_name().to_string_lossy().into_owned()).collect())
        .unwrap_or_default();
    v.retain(|n| n.starts_with("step-") && n.ends_with(".safetensors"));
    v.sort();
    v
}

/// Runs `t` for `n` steps (never interrupted) and returns their reports.
pub fn run_steps(t: &mut gdrf_core::train::Trainer, n: i64) -> Vec<gdrf_core::train::StepReport> {
    let mut reports = Vec::new();
    let never = std::sync::atomic::AtomicBool::new(false);
    let limits = gdrf_core::train::RunLimits { steps: Some(n), seconds: None };
    let stopped = t.run(limits, &never, |r, _| reports.push(r.clone())).unwrap();
    assert_eq!(stopped, gdrf_core::train::Stopped::Limit);
    reports
}

/// A var store's variables, detached copies sorted by name.
pub fn params(vs: &tch::nn::VarStore) -> Vec<(String, Tensor)> {
    let mut v: Vec<_> = vs.variables().into_iter().map(|(n, t)| (n, t.detach().copy())).collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

/// Whether two [`params`] lists hold the same names and bit-equal values.
pub fn same_params(a: &[(String, Tensor)], b: &[(String, Tensor)]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.0 == y.0 && x.1.equal(&y.1))
}

/// Copies the folder `from` to `to`, recursively.
pub fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &to.join(e.file_name()));
        } else {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}
