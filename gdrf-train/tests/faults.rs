//! gdrf-train under faults: SIGKILL at any moment (during a step, while a checkpoint, a
//! preview or the EMA export is being written, or leaving a torn metrics line), a write
//! that fails for lack of space, and a read-only run directory. Nothing that was saved is
//! lost, no temporary file stays, and the resumed run goes on as if never stopped.
//!
//! The SIGKILL trials are also the many-trial command of docs/testing.md, "Reliability: nothing lost under faults":
//! `GDRF_KILL_TRIALS=N` (default 10, two per kind of moment), `GDRF_KILL_SEED` (the kill
//! moments' seed) and `GDRF_KILL_REPORT=FILE` (the counts as JSON) set it up.
#[path = "../../gdrf-core/tests/common/mod.rs"]
mod common;

use common::{checkpoint_names, tiny_run_config, TempDir};
use std::collections::BTreeMap;
use std::os::unix::fs::{MetadataExt, PermissionsExt};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_gdrf-train"))
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

/// How many steps a run logged (its torn line, if any, not counted).
fn logged_steps(run: &Path) -> i64 {
    let text = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap_or_default();
    let steps = text.lines().filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok()?["step"].as_i64());
    steps.max().map_or(0, |s| s + 1)
}

/// Files whose name marks them as a killed writer's temporary (`.NAME.tmp-PID`), anywhere
/// in the run folder.
fn temporaries(dir: &Path) -> Vec<PathBuf> {
    let mut found = Vec::new();
    for e in std::fs::read_dir(dir).into_iter().flatten().filter_map(|e| e.ok()) {
        let p = e.path();
        if p.is_dir() {
            found.extend(temporaries(&p));
        } else if gdrf_core::paths::is_temporary(&e.file_name().to_string_lossy()) {
            found.push(p);
        }
    }
    found
}

/// The last checkpoint of a 10-step run: its header without the training time, and its
/// tensors' bytes by name.
fn final_state(run: &Path) -> Option<(serde_json::Value, BTreeMap<String, Vec<u8>>)> {
    let c = gdrf_core::checkpoint::load(&run.join("checkpoints/step-00000010.safetensors")).ok()?;
    let mut header = serde_json::to_value(&c.header).unwrap();
    // The seconds trained, in the progress and rounded in the header's info, are the one
    // thing a run may not repeat: on a slow machine they round differently run to run.
    header["training"]["progress"].as_object_mut()?.remove("train_seconds")?;
    header["info"].as_object_mut()?.remove("train_seconds")?;
    let bytes = |t: &tch::Tensor| {
        let mut v = vec![0u8; t.numel() * t.kind().elt_size_in_bytes()];
        t.copy_data_u8(&mut v, t.numel());
        v
    };
    Some((header, c.tensors.iter().map(|(n, t)| (n.clone(), bytes(t))).collect()))
}

/// The moment a SIGKILL lands, told by what it leaves behind.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "snake_case")]
enum Moment {
    /// Between writes: training, sampling codes, logging (no temporary file left).
    Step,
    /// While checkpoints/.step-N.safetensors.tmp-PID was being written or flushed.
    Checkpoint,
    /// While the EMA generator (.generator.safetensors.tmp-PID) was being exported.
    Export,
    /// While a preview image (samples/.NAME.png.tmp-PID) was being written.
    Preview,
    /// While a new run's resolved config (.config.toml.tmp-PID) was being written.
    Config,
    /// A torn last line of metrics.jsonl. One append is one write(2), which a SIGKILL
    /// cannot split, so the harness tears the line itself after the kill (what a power
    /// cut or a full disk can leave).
    TornMetrics,
}

const MOMENTS: [Moment; 5] = [Moment::Step, Moment::Checkpoint, Moment::Export, Moment::Preview, Moment::TornMetrics];

/// Which write a temporary file belongs to.
fn moment_of(run: &Path, tmp: &Path) -> Moment {
    let name = tmp.file_name().unwrap().to_string_lossy();
    match tmp.parent() {
        Some(d) if d == run.join("checkpoints") => Moment::Checkpoint,
        Some(d) if d == run.join("samples") => Moment::Preview,
        _ if name.starts_with(".generator.safetensors") => Moment::Export,
        _ if name.starts_with(".config.toml") => Moment::Config,
        _ => panic!("a temporary file of no known writer: {}", tmp.display()),
    }
}

/// xorshift64: the kill moments are the same on every run with the same seed.
struct Draws(u64);

impl Draws {
    fn unit(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}

#[derive(Default, serde::Serialize)]
struct Report {
    /// Attempts (a missed write is aimed at again, up to twice).
    trials: usize,
    /// Runs that ended before the moment aimed at came (no kill; not counted in `kills`).
    finished_before_the_kill: usize,
    /// Kills by the moment they landed in (told by the temporary file they left).
    kills: BTreeMap<String, usize>,
    /// Kills aimed at a write that landed elsewhere (the write ended first), each tried again.
    aimed_at_a_write_but_landed_between: usize,
    resumed_from_a_checkpoint: usize,
    /// Killed before the first checkpoint: started again from step 0.
    restarted: usize,
    /// Finished steps lost per trial (logged before the kill, minus the step resumed at).
    steps_lost: BTreeMap<i64, usize>,
    temporaries_left_after_resume: usize,
    /// Resumed runs whose metrics or final state differ from the uninterrupted run's.
    diverged: usize,
    failures: Vec<String>,
}

/// SIGKILL, which gives no warning, at moments drawn from a fixed seed over a short run
/// that checkpoints every 2 steps and renders previews every 3. Each kind of moment is
/// aimed at in turn, after a random number of logged steps: a random instant, the first
/// write of a checkpoint, an export or a preview after it (the harness watches for its
/// temporary file and kills as soon as it appears), or a torn metrics line. Every killed run must resume from its newest complete
/// checkpoint, lose at most one checkpoint interval, end with the uninterrupted run's
/// metrics (every step once, no torn line) and final checkpoint exactly, and leave no
/// temporary file.
#[test]
fn a_run_killed_at_any_moment_resumes_exactly() {
    let trials: usize = std::env::var("GDRF_KILL_TRIALS").map_or(10, |v| v.parse().expect("GDRF_KILL_TRIALS"));
    let seed: u64 =
        std::env::var("GDRF_KILL_SEED").map_or(0x2545_f491_4f6c_dd1d, |v| v.parse().expect("GDRF_KILL_SEED"));
    let dir = TempDir::new("faults-kill").unwrap();
    let text = std::fs::read_to_string(tiny_run_config(&dir.0, 10))
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
    let want_state = final_state(&reference).expect("the uninterrupted run's last checkpoint");

    let mut draws = Draws(seed | 1);
    let mut report = Report::default();
    // A kill that missed the write it aimed at (the write ended first) is tried again, up
    // to twice; every attempt is a trial and is checked.
    let mut plan: std::collections::VecDeque<(Moment, u32)> =
        (0..trials).map(|i| (MOMENTS[i % MOMENTS.len()], 0)).collect();
    let mut trial = 0;
    while let Some((aim, attempt)) = plan.pop_front() {
        trial += 1;
        report.trials += 1;
        let again_if_missed = |plan: &mut std::collections::VecDeque<(Moment, u32)>| {
            if attempt < 2 {
                plan.push_front((aim, attempt + 1));
            }
        };
        let run = dir.path(&format!("run-{trial}"));
        // The run's own progress is the clock (metrics lines written), so that a loaded
        // machine moves the moments with the run: `after` lines, then `at` more time.
        let after = (draws.unit() * 9.0) as usize;
        let at = match aim {
            Moment::Step if after == 0 => whole.mul_f64(0.5 * draws.unit()),
            Moment::Step => whole.mul_f64(0.1 * draws.unit()),
            _ => Duration::ZERO,
        };
        let after = if aim == Moment::TornMetrics { after.max(1) } else { after };
        let mut child = bin()
            .arg("--config")
            .arg(&cfg)
            .arg("--run-dir")
            .arg(&run)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        while child.try_wait().unwrap().is_none() && logged_steps(&run) < after as i64 {
            std::thread::sleep(Duration::from_micros(200));
        }
        let t0 = Instant::now();
        while t0.elapsed() < at {
            std::thread::sleep(Duration::from_micros(200));
        }
        if matches!(aim, Moment::Checkpoint | Moment::Export | Moment::Preview) {
            // Watch for the write's temporary file (busy: a write lasts milliseconds).
            while child.try_wait().unwrap().is_none() && !temporaries(&run).iter().any(|t| moment_of(&run, t) == aim) {}
        }
        if child.try_wait().unwrap().is_some() {
            // The run ended before the moment came: nothing to recover from.
            report.finished_before_the_kill += 1;
            again_if_missed(&mut plan);
            let _ = std::fs::remove_dir_all(&run);
            continue;
        }
        child.kill().unwrap(); // SIGKILL
        child.wait().unwrap();
        let left = temporaries(&run);
        let landed = left.first().map_or(Moment::Step, |t| moment_of(&run, t));
        let landed = if aim == Moment::TornMetrics && landed == Moment::Step {
            let path = run.join("metrics.jsonl");
            let text = std::fs::read_to_string(&path).unwrap_or_default();
            match text.lines().last() {
                Some(last) => {
                    std::fs::write(&path, format!("{text}{}", &last[..last.len() / 2])).unwrap();
                    Moment::TornMetrics
                }
                None => Moment::Step,
            }
        } else {
            landed
        };
        if matches!(aim, Moment::Checkpoint | Moment::Export | Moment::Preview) && landed != aim {
            report.aimed_at_a_write_but_landed_between += 1;
            again_if_missed(&mut plan);
        }
        *report.kills.entry(serde_json::to_value(landed).unwrap().as_str().unwrap().to_string()).or_default() += 1;

        let logged = logged_steps(&run);
        let newest = checkpoint_names(&run)
            .last()
            .map(|n| n["step-".len()..n.len() - ".safetensors".len()].parse::<i64>().unwrap());
        let again = match newest {
            None => bin().arg("--config").arg(&cfg).arg("--run-dir").arg(&run).arg("--force").output().unwrap(),
            Some(_) => bin().arg("--resume").arg(&run).output().unwrap(),
        };
        let said = String::from_utf8_lossy(&again.stdout).into_owned();
        let what = format!("trial {trial} (aimed at {aim:?} after {after} steps and {at:?}, landed in {landed:?})");
        if !again.status.success() {
            report.failures.push(format!("{what}: the resume failed: {}", String::from_utf8_lossy(&again.stderr)));
            continue;
        }
        let from = match newest {
            None => {
                report.restarted += 1;
                0
            }
            Some(step) => {
                report.resumed_from_a_checkpoint += 1;
                if !said.contains(&format!("at step {step}/")) {
                    report
                        .failures
                        .push(format!("{what}: not resumed from the newest checkpoint, step {step}: {said}"));
                }
                step
            }
        };
        let lost = logged.max(from) - from;
        *report.steps_lost.entry(lost).or_default() += 1;
        println!("{what}: {logged} steps logged, resumed at step {from}");
        if lost > 2 {
            report
                .failures
                .push(format!("{what}: {logged} steps done, resumed at {from}: more than one interval lost"));
        }
        let left = temporaries(&run);
        report.temporaries_left_after_resume += left.len();
        if !left.is_empty() {
            report.failures.push(format!("{what}: temporary files left: {left:?}"));
        }
        if metrics_without_times(&run) != want || final_state(&run).as_ref() != Some(&want_state) {
            report.diverged += 1;
            report
                .failures
                .push(format!("{what}: the metrics or the final checkpoint differ from the uninterrupted run's"));
        }
        let _ = std::fs::remove_dir_all(&run);
    }
    let json = serde_json::to_string_pretty(&report).unwrap();
    println!("{json}");
    if let Ok(path) = std::env::var("GDRF_KILL_REPORT") {
        std::fs::write(&path, &json).unwrap();
    }
    assert!(report.failures.is_empty(), "{json}");
    if trials >= MOMENTS.len() {
        for m in MOMENTS {
            let name = serde_json::to_value(m).unwrap().as_str().unwrap().to_string();
            assert!(report.kills.get(&name).is_some_and(|&n| n > 0), "no kill landed in {name}: {json}");
        }
    }
}

/// A checkpoint that cannot be written (here: a file-size limit, what a full disk does to a
/// write) stops training with exit 1 and an error naming the file; the checkpoint before it
/// is intact, no temporary file is left, and the run resumes from it.
#[test]
fn a_checkpoint_that_cannot_be_written_stops_the_run_and_keeps_the_last_one() {
    let dir = TempDir::new("faults-full").unwrap();
    let cfg = tiny_run_config(&dir.0, 100);
    let run = dir.path("run");
    let out = bin().arg("--config").arg(&cfg).arg("--run-dir").arg(&run).args(["--steps", "2"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let listed = checkpoint_names(&run);
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
    assert_eq!(checkpoint_names(&run), listed, "no new or temporary checkpoint file");
    assert_eq!(std::fs::read(run.join("checkpoints/step-00000002.safetensors")).unwrap(), before);
    assert_eq!(temporaries(&run), Vec::<PathBuf>::new());
    let again = bin().arg("--resume").arg(&run).args(["--steps", "2"]).output().unwrap();
    assert!(again.status.success(), "{}", String::from_utf8_lossy(&again.stderr));
    assert_eq!(checkpoint_names(&run).last().map(String::as_str), Some("step-00000004.safetensors"));
}

/// `gdrf-train` run as a user for whom folders without write permission are read-only:
/// the tests' own user, or `nobody` (owning the run) when the tests run as root, whom
/// permissions do not stop.
fn as_restricted_user(cmd: &mut Command, run: &Path) {
    let probe = run.join(".owner-probe");
    std::fs::write(&probe, b"").unwrap();
    let root = std::fs::metadata(&probe).unwrap().uid() == 0;
    std::fs::remove_file(&probe).unwrap();
    if root {
        const NOBODY: u32 = 65534;
        fn chown_all(p: &Path) {
            std::os::unix::fs::chown(p, Some(NOBODY), Some(NOBODY)).unwrap();
            if p.is_dir() {
                for e in std::fs::read_dir(p).unwrap() {
                    chown_all(&e.unwrap().path());
                }
            }
        }
        chown_all(run);
        cmd.uid(NOBODY).gid(NOBODY);
    }
}

fn set_mode(p: &Path, mode: u32) {
    std::fs::set_permissions(p, std::fs::Permissions::from_mode(mode)).unwrap();
}

/// A run directory that is read-only: resuming stops at once with exit 1 and an error that
/// names what it could not write; the checkpoint is intact. Its checkpoints folder alone
/// read-only (as when a disk is remounted read-only under a running job): the steps run,
/// the checkpoint write fails naming the file, and the run resumes exactly once writable.
#[test]
fn a_read_only_run_directory_is_an_error_naming_the_file() {
    let dir = TempDir::new("faults-read-only").unwrap();
    let cfg = tiny_run_config(&dir.0, 100);
    let run = dir.path("run");
    let out = bin().arg("--config").arg(&cfg).arg("--run-dir").arg(&run).args(["--steps", "2"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let listed = checkpoint_names(&run);
    let ckpt = run.join("checkpoints/step-00000002.safetensors");
    let before = std::fs::read(&ckpt).unwrap();
    let metrics_before = metrics_without_times(&run);

    for (read_only, names) in [
        (vec![run.clone(), run.join("checkpoints")], "metrics.jsonl"),
        (vec![run.join("checkpoints")], "step-00000004.safetensors"),
    ] {
        let mut cmd = bin();
        cmd.arg("--resume").arg(&run).args(["--steps", "2"]);
        as_restricted_user(&mut cmd, &run);
        for d in &read_only {
            set_mode(d, 0o555);
        }
        let out = cmd.output().unwrap();
        for d in &read_only {
            set_mode(d, 0o755);
        }
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "read-only {read_only:?}: {err}");
        assert!(err.contains(names) && err.contains("ermission denied"), "read-only {read_only:?}: {err}");
        assert_eq!(checkpoint_names(&run), listed, "read-only {read_only:?}");
        assert_eq!(std::fs::read(&ckpt).unwrap(), before);
        assert_eq!(temporaries(&run), Vec::<PathBuf>::new());
    }
    let again = bin().arg("--resume").arg(&run).args(["--steps", "2"]).output().unwrap();
    assert!(again.status.success(), "{}", String::from_utf8_lossy(&again.stderr));
    assert_eq!(checkpoint_names(&run).last().map(String::as_str), Some("step-00000004.safetensors"));
    let after = metrics_without_times(&run);
    assert_eq!(after.len(), 4);
    assert_eq!(after[..2], metrics_before[..]);
}
