//! gdrf-train from the command line: config errors name the key, SIGTERM (what Ctrl-C
//! and schedulers send) writes a checkpoint of the last finished step and `--resume`
//! continues from it, an existing run is never overwritten silently, a run directory in
//! use is refused to a second process, a write that fails for lack of space stops the run
//! with an error naming the file and the last checkpoint intact, a run killed with SIGKILL
//! at any moment resumes exactly, and `plot` draws.
#[path = "../../gdrf-core/tests/common/mod.rs"]
mod common;

use common::TempDir;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_gdrf-train"))
}

fn write_config(dir: &Path, total_steps: i64) -> PathBuf {
    let text = common::tiny_training_toml(
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

fn metrics_lines(run: &Path) -> usize {
    std::fs::read_to_string(run.join("metrics.jsonl")).map(|s| s.lines().count()).unwrap_or(0)
}

fn checkpoints(run: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(run.join("checkpoints"))
        .map(|d| d.filter_map(|e| e.ok()).map(|e| e.file_name().to_string_lossy().into_owned()).collect())
        .unwrap_or_default();
    v.sort();
    v
}

#[test]
fn config_errors_name_the_key_and_the_expectation() {
    let dir = TempDir::new("cli-config").unwrap();
    let good = std::fs::read_to_string(write_config(&dir.0, 10)).unwrap();
    for (edit, key, expected) in [
        (good.replace("log_interval = 1", "log_intervall = 1"), "log_intervall", "expected one of"),
        (good.replace("batch_size = 2", "batch_size = \"two\""), "batch_size", "expected i64"),
        (good.replace("resolution = 8\n", "resolution = 12\n"), "stages[0].resolution", "power of two"),
        (format!("{good}\n[optim]\ngrad_clip = -1.0\n"), "optim.grad_clip", "positive"),
    ] {
        let path = dir.path("bad.toml");
        std::fs::write(&path, edit).unwrap();
        let out = bin().arg("--config").arg(&path).arg("--run-dir").arg(dir.path("run")).output().unwrap();
        assert_eq!(out.status.code(), Some(1));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(key) && err.contains(expected) && err.contains("bad.toml"), "{key}: {err}");
    }
    let out = bin().arg("--print-config").arg(dir.path("tiny.toml")).output().unwrap();
    assert!(out.status.success());
    let printed = String::from_utf8_lossy(&out.stdout);
    assert!(printed.contains("grad_clip = 0.3") && printed.contains("[[stages]]"), "{printed}");
    // A bare file name, run from the config's folder: paths resolve against that folder.
    let out = bin().current_dir(&dir.0).arg("--print-config").arg("tiny.toml").output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let printed = String::from_utf8_lossy(&out.stdout);
    let want = format!("path = {:?}", std::path::absolute(dir.path("data")).unwrap().display().to_string());
    assert!(printed.contains(&want), "{want} not in {printed}");
}

#[test]
fn sigterm_checkpoints_the_last_step_and_resume_continues_from_it() {
    let dir = TempDir::new("cli-sigterm").unwrap();
    let config = write_config(&dir.0, 100_000);
    let run = dir.path("run");
    let child = bin()
        .arg("--config")
        .arg(&config)
        .arg("--run-dir")
        .arg(&run)
        .arg("--quiet")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let start = Instant::now();
    while metrics_lines(&run) < 3 {
        assert!(start.elapsed() < Duration::from_secs(120), "no training progress within 2 minutes");
        std::thread::sleep(Duration::from_millis(50));
    }
    // While it trains, the folder is its own: neither a resume nor --force gets in.
    for args in [vec!["--resume".into(), run.clone().into_os_string()], {
        let mut v: Vec<std::ffi::OsString> = vec!["--config".into(), config.clone().into_os_string()];
        v.extend(["--run-dir".into(), run.clone().into_os_string(), "--force".into()]);
        v
    }] {
        let out = bin().args(&args).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{args:?}: {err}");
        assert!(err.contains("in use by another gdrf-train") && err.contains(&child.id().to_string()), "{err}");
    }
    assert!(metrics_lines(&run) >= 3, "--force removed the running run's metrics");
    let status = Command::new("kill").arg("-TERM").arg(child.id().to_string()).status().unwrap();
    assert!(status.success());
    let out = child.wait_with_output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(130), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("interrupted at step"), "{stdout}");
    // The checkpoint is of the last finished step: one past the last logged step.
    let logged = metrics_lines(&run);
    let last = checkpoints(&run).pop().unwrap();
    assert_eq!(last, format!("step-{logged:08}.safetensors"));

    let out = bin().arg("--resume").arg(&run).args(["--steps", "2", "--quiet"]).output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains(&format!("resuming run {} at step {logged}/", run.display())), "{stdout}");
    assert_eq!(metrics_lines(&run), logged + 2);
    assert_eq!(checkpoints(&run).pop().unwrap(), format!("step-{:08}.safetensors", logged + 2));

    // A new run in the same folder is refused without --force.
    let out = bin().arg("--config").arg(&config).arg("--run-dir").arg(&run).arg("--steps").arg("1").output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("--resume"));

    let out = bin().arg("plot").arg(&run).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let img = image::open(run.join("losses.png")).unwrap();
    assert_eq!((img.width(), img.height()), (4 * 360, 2 * 240));
}

#[test]
fn a_rollback_is_reported_where_the_run_is_watched() {
    // Three non-finite steps in a row roll the run back; the console (here a pipe, so the
    // progress bar is hidden) says so, not only metrics.jsonl.
    let dir = TempDir::new("cli-rollback").unwrap();
    let config = write_config(&dir.0, 4);
    let mut text = std::fs::read_to_string(&config).unwrap();
    text.push_str("\n[debug]\ninject_nonfinite_steps = [1, 2, 3]\n\n[guard]\nrollback_after = 3\n");
    std::fs::write(&config, text).unwrap();
    let run = dir.path("run");
    let out = bin().arg("--config").arg(&config).arg("--run-dir").arg(&run).output().unwrap();
    let said = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{said}");
    assert!(said.contains("step 3: non-finite steps in a row; rolled back to step 0 with lr × 0.5"), "{said}");
}

/// A checkpoint that cannot be written (here: a file-size limit, what a full disk does to a
/// write) stops training with exit 1 and an error naming the file; the checkpoint before it
/// is intact, no temporary file is left, and the run resumes from it.
#[test]
fn a_checkpoint_that_cannot_be_written_stops_the_run_and_keeps_the_last_one() {
    let dir = TempDir::new("cli-full").unwrap();
    let cfg = write_config(&dir.0, 100);
    let run = dir.path("run");
    let out = bin().arg("--config").arg(&cfg).arg("--run-dir").arg(&run).args(["--steps", "2"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let listed = checkpoints(&run);
    assert_eq!(listed.last().map(String::as_str), Some("step-00000002.safetensors"), "{listed:?}");
    let before = std::fs::read(run.join("checkpoints/step-00000002.safetensors")).unwrap();
    // The limit lets the metrics lines through and stops the checkpoint (hundreds of KB).
    // SIGXFSZ is ignored, as a process under a quota or on a full disk sees no signal:
    // the write itself fails (EFBIG; ENOSPC on a full disk).
    let limited = Command::new("sh")
        .arg("-c")
        .arg(r#"trap "" XFSZ; ulimit -f 64; exec "$0" "$@""#)
        .arg(env!("CARGO_BIN_EXE_gdrf-train"))
        .arg("--resume")
        .arg(&run)
        .args(["--steps", "2"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&limited.stderr);
    assert_eq!(limited.status.code(), Some(1), "{err}");
    assert!(err.contains("step-00000004.safetensors") && err.contains("too large"), "{err}");
    assert_eq!(checkpoints(&run), listed, "no new or temporary checkpoint file");
    assert_eq!(std::fs::read(run.join("checkpoints/step-00000002.safetensors")).unwrap(), before);
    let leftovers: Vec<_> = std::fs::read_dir(&run)
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains(".tmp-"))
        .collect();
    assert!(leftovers.is_empty(), "temporary files left: {leftovers:?}");
    let again = bin().arg("--resume").arg(&run).args(["--steps", "2"]).output().unwrap();
    assert!(again.status.success(), "{}", String::from_utf8_lossy(&again.stderr));
    assert_eq!(checkpoints(&run).last().map(String::as_str), Some("step-00000004.safetensors"));
}

/// The metrics lines of a run without the timing keys, in file order (a torn or repeated
/// line would show as a difference).
fn metrics_without_times(run: &Path) -> Vec<serde_json::Value> {
    let text = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap_or_default();
    text.lines()
        .map(|l| {
            let mut v: serde_json::Value = serde_json::from_str(l).unwrap_or_else(|e| panic!("torn line {l:?}: {e}"));
            let m = v.as_object_mut().unwrap();
            m.remove("step_seconds");
            m.remove("images_per_second");
            v
        })
        .collect()
}

/// Files whose name marks them as a killed writer's temporary (`.NAME.tmp-PID`), anywhere
/// in the run folder.
fn temporaries(dir: &Path) -> Vec<PathBuf> {
    let mut found = Vec::new();
    for e in std::fs::read_dir(dir).unwrap().filter_map(|e| e.ok()) {
        let p = e.path();
        if p.is_dir() {
            found.extend(temporaries(&p));
        } else if gdrf_core::paths::is_temporary(&e.file_name().to_string_lossy()) {
            found.push(p);
        }
    }
    found
}

/// SIGKILL, which gives no warning, at moments drawn from a fixed seed over a short run
/// that checkpoints every 2 steps and renders previews every 3: each killed run resumes
/// from its newest complete checkpoint, loses at most one checkpoint interval, and ends
/// with the uninterrupted run's metrics exactly (every step once, no torn line) and no
/// temporary file left.
#[test]
fn a_run_killed_at_any_moment_resumes_exactly() {
    let dir = TempDir::new("cli-kill").unwrap();
    let text = std::fs::read_to_string(write_config(&dir.0, 10))
        .unwrap()
        .replace("checkpoint_interval = 1000", "checkpoint_interval = 2")
        .replace("sample_interval = 0", "sample_interval = 3");
    let cfg = dir.path("kill.toml");
    std::fs::write(&cfg, text).unwrap();
    let reference = dir.path("reference");
    let start = Instant::now();
    let out = bin().arg("--config").arg(&cfg).arg("--run-dir").arg(&reference).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let (whole, want) = (start.elapsed(), metrics_without_times(&reference));
    assert_eq!(want.len(), 10);
    let mut state = 0x2545_f491_4f6c_dd1du64;
    for trial in 0..4 {
        // xorshift64: the kill moments are the same on every run of the suite.
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        let at = whole.mul_f64((state % 1000) as f64 / 1000.0);
        let run = dir.path(&format!("run-{trial}"));
        let mut child = bin()
            .arg("--config")
            .arg(&cfg)
            .arg("--run-dir")
            .arg(&run)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(at);
        child.kill().unwrap(); // SIGKILL
        child.wait().unwrap();
        let logged = metrics_without_times(&run).last().and_then(|l| l["step"].as_i64()).map_or(0, |s| s + 1);
        let again = if checkpoints(&run).is_empty() {
            bin().arg("--config").arg(&cfg).arg("--run-dir").arg(&run).arg("--force").output().unwrap()
        } else {
            bin().arg("--resume").arg(&run).output().unwrap()
        };
        let said = String::from_utf8_lossy(&again.stdout).into_owned();
        assert!(again.status.success(), "trial {trial} (killed at {at:?}): {}", String::from_utf8_lossy(&again.stderr));
        let from = said
            .split_once("at step ")
            .and_then(|(_, rest)| rest.split('/').next())
            .and_then(|n| n.parse::<i64>().ok())
            .unwrap_or(0);
        println!("trial {trial}: killed after {at:?} of {whole:?}, {logged} steps logged, resumed at step {from}");
        assert!(logged - from <= 2, "trial {trial}: {logged} steps done, resumed at {from}: {said}");
        assert_eq!(metrics_without_times(&run), want, "trial {trial} (killed at {at:?}, resumed at {from})");
        assert_eq!(temporaries(&run), Vec::<PathBuf>::new(), "trial {trial}");
    }
}
