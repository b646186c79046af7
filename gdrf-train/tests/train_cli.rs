//! gdrf-train from the command line: config errors name the key, SIGTERM (what Ctrl-C
//! and schedulers send) writes a checkpoint of the last finished step and `--resume`
//! continues from it, an existing run is never overwritten silently, a run directory in
//! use is refused to a second process, and `plot` draws. Faults (SIGKILL, full and
//! read-only disks) are in faults.rs.
#[path = "../../gdrf-core/tests/common/mod.rs"]
mod common;

use common::TempDir;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_gdrf-train"))
}

fn metrics_lines(run: &Path) -> usize {
    std::fs::read_to_string(run.join("metrics.jsonl")).map(|s| s.lines().count()).unwrap_or(0)
}

#[test]
fn config_errors_name_the_key_and_the_expectation() {
    let dir = TempDir::new("cli-config").unwrap();
    let good = std::fs::read_to_string(common::tiny_run_config(&dir.0, 10)).unwrap();
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
    let config = common::tiny_run_config(&dir.0, 100_000);
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
    let last = common::checkpoint_names(&run).pop().unwrap();
    assert_eq!(last, format!("step-{logged:08}.safetensors"));

    let out = bin().arg("--resume").arg(&run).args(["--steps", "2", "--quiet"]).output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains(&format!("resuming run {} at step {logged}/", run.display())), "{stdout}");
    assert_eq!(metrics_lines(&run), logged + 2);
    assert_eq!(common::checkpoint_names(&run).pop().unwrap(), format!("step-{:08}.safetensors", logged + 2));

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
    let config = common::tiny_run_config(&dir.0, 4);
    let mut text = std::fs::read_to_string(&config).unwrap();
    text.push_str("\n[debug]\ninject_nonfinite_steps = [1, 2, 3]\n\n[guard]\nrollback_after = 3\n");
    std::fs::write(&config, text).unwrap();
    let run = dir.path("run");
    let out = bin().arg("--config").arg(&config).arg("--run-dir").arg(&run).output().unwrap();
    let said = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{said}");
    assert!(said.contains("step 3: non-finite steps in a row; rolled back to step 0 with lr × 0.5"), "{said}");
}

/// gdrf-train as two ranks on this machine (`--nproc 2`, rendezvous on a free loopback
/// port), a rank waiting at most `timeout` seconds for the other.
fn two_ranks(timeout: u64) -> Command {
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let mut c = bin();
    c.args(["--nproc", "2", "--master-port", &port.to_string(), "--dist-timeout", &timeout.to_string()]);
    c
}

/// One multi-process run at a time: a free port picked for one run's rendezvous could
/// otherwise be taken by another run's Gloo connections before its store binds it.
static ONE_GROUP_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// `--nproc 2` trains one run as two ranks (each half of every batch, rank 0 writing),
/// and a single process resumes it; and the reverse, a one-process run resumed by two
/// ranks. Their losses follow the ones of a run trained in one process throughout, within
/// float32 tolerance.
#[test]
fn two_ranks_and_one_process_resume_each_others_runs() {
    let _one = ONE_GROUP_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = TempDir::new("cli-nproc").unwrap();
    let text = common::tiny_two_rank_config(&dir.0, 100);
    let cfg = dir.path("nproc.toml");
    std::fs::write(&cfg, text).unwrap();
    let losses = |run: &Path| -> Vec<(i64, f64, f64)> {
        let text = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
        text.lines()
            .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
            .map(|v| (v["step"].as_i64().unwrap(), v["d_total"].as_f64().unwrap(), v["g_total"].as_f64().unwrap()))
            .collect()
    };
    let alone = dir.path("alone");
    let out = bin().arg("--config").arg(&cfg).arg("--run-dir").arg(&alone).args(["--steps", "5"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let run = dir.path("ranks");
    let out =
        two_ranks(120).arg("--config").arg(&cfg).arg("--run-dir").arg(&run).args(["--steps", "3"]).output().unwrap();
    let said = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{said}");
    assert!(said.contains("2 ranks"), "{said}");
    assert_eq!(common::checkpoint_names(&run).last().map(String::as_str), Some("step-00000003.safetensors"));
    let out = bin().arg("--resume").arg(&run).args(["--steps", "2"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    // The reverse: one process, then two ranks.
    let reverse = dir.path("reverse");
    let out = bin().arg("--config").arg(&cfg).arg("--run-dir").arg(&reverse).args(["--steps", "3"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let out = two_ranks(120).arg("--resume").arg(&reverse).args(["--steps", "2"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let want = losses(&alone);
    for (what, run) in [("two ranks, then one process", &run), ("one process, then two ranks", &reverse)] {
        let got = losses(run);
        assert_eq!(got.len(), 5, "{what}: {got:?}");
        for ((s, d, g), (s2, d2, g2)) in want.iter().zip(&got) {
            assert_eq!(s, s2);
            for (a, b) in [(d, d2), (g, g2)] {
                assert!((a - b).abs() <= 1e-4 * a.abs().max(1.0), "{what}, step {s}: {a} alone, {b} here");
            }
        }
    }
}

/// Three non-finite steps in a row on both ranks roll both back together: they stay in
/// their group, rank 0 alone logs the rollback, and the run finishes.
#[test]
fn two_ranks_roll_back_together() {
    let _one = ONE_GROUP_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = TempDir::new("cli-nproc-rollback").unwrap();
    let mut text = common::tiny_two_rank_config(&dir.0, 6);
    text.push_str("\n[debug]\ninject_nonfinite_steps = [1, 2, 3]\n\n[guard]\nrollback_after = 3\n");
    let cfg = dir.path("rollback.toml");
    std::fs::write(&cfg, text).unwrap();
    let run = dir.path("run");
    let out = two_ranks(120).arg("--config").arg(&cfg).arg("--run-dir").arg(&run).output().unwrap();
    let said = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{said}");
    let text = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    let lines: Vec<serde_json::Value> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let rollbacks = lines.iter().filter(|l| l["event"] == "rollback").count();
    let steps: Vec<i64> = lines.iter().filter(|l| l["event"].is_null()).map(|l| l["step"].as_i64().unwrap()).collect();
    assert_eq!(rollbacks, 1, "{text}");
    assert_eq!(steps, [0, 1, 2, 3, 4, 5], "{text}");
    // After the rollback the ranks still train as one process does (averaged halves).
    let alone = dir.path("alone");
    let out = bin().arg("--config").arg(&cfg).arg("--run-dir").arg(&alone).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let totals = |text: &str| -> Vec<(f64, f64)> {
        text.lines()
            .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
            .filter(|l| l["event"].is_null())
            .map(|l| (l["d_total"].as_f64().unwrap(), l["g_total"].as_f64().unwrap()))
            .collect()
    };
    let want = totals(&std::fs::read_to_string(alone.join("metrics.jsonl")).unwrap());
    for (step, ((d, g), (d2, g2))) in want.iter().zip(totals(&text)).enumerate() {
        for (a, b) in [(d, d2), (g, g2)] {
            assert!((a - b).abs() <= 1e-4 * a.abs().max(1.0), "step {step}: {a} alone, {b} as two ranks");
        }
    }
}

/// The pids of `launcher`'s children whose environment sets `RANK=rank` (Linux).
fn rank_pids(launcher: u32, rank: usize) -> Vec<u32> {
    let children = std::fs::read_to_string(format!("/proc/{launcher}/task/{launcher}/children")).unwrap_or_default();
    children
        .split_whitespace()
        .filter_map(|p| p.parse::<u32>().ok())
        .filter(|p| {
            std::fs::read(format!("/proc/{p}/environ"))
                .is_ok_and(|env| env.split(|&b| b == 0).any(|v| v == format!("RANK={rank}").as_bytes()))
        })
        .collect()
}

/// A rank killed mid-run (SIGKILL, after the step-5 checkpoint) makes the other rank
/// exit with an error that says the peer is gone, well within its timeout; the launcher
/// names the killed rank; and the newest checkpoint still resumes, in one process. A rank
/// that hangs instead (SIGSTOP) makes the other fail at --dist-timeout, and the launcher
/// kills it after the grace period.
#[test]
fn a_killed_or_hung_rank_stops_the_run_with_an_error_naming_it() {
    let _one = ONE_GROUP_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = TempDir::new("cli-nproc-kill").unwrap();
    let text =
        common::tiny_two_rank_config(&dir.0, 100_000).replace("checkpoint_interval = 1000", "checkpoint_interval = 5");
    let cfg = dir.path("kill.toml");
    std::fs::write(&cfg, text).unwrap();
    for (signal, timeout) in [("KILL", 60u64), ("STOP", 4)] {
        let run = dir.path(&format!("run-{signal}"));
        let launcher = two_ranks(timeout)
            .arg("--config")
            .arg(&cfg)
            .arg("--run-dir")
            .arg(&run)
            .arg("--quiet")
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let start = Instant::now();
        while !common::checkpoint_names(&run).iter().any(|n| n == "step-00000005.safetensors") {
            assert!(start.elapsed() < Duration::from_secs(120), "no step-5 checkpoint after 2 minutes");
            std::thread::sleep(Duration::from_millis(20));
        }
        let victim = rank_pids(launcher.id(), 1);
        assert_eq!(victim.len(), 1, "rank 1's process among the launcher's children");
        let ok = Command::new("kill").args([&format!("-{signal}"), &victim[0].to_string()]).status().unwrap();
        assert!(ok.success());
        let signalled = Instant::now();
        let mut launcher = launcher;
        // The survivor's next collective fails at once (a closed connection) or after the
        // timeout (silence); the launcher waits 10 s more for a rank that is still running.
        let limit = Duration::from_secs(timeout.min(10) + 10 + 30);
        while launcher.try_wait().unwrap().is_none() {
            if signalled.elapsed() > limit {
                let _ = launcher.kill();
                let _ = Command::new("kill").args(["-KILL", &victim[0].to_string()]).status();
                panic!("SIG{signal}: the run still going {limit:?} after rank 1 was signalled");
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let took = signalled.elapsed();
        let out = launcher.wait_with_output().unwrap();
        let said = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
        println!("SIG{signal}: exited {:?} after {took:.1?}\n{said}", out.status.code());
        assert_eq!(out.status.code(), Some(1), "{said}");
        if signal == "KILL" {
            assert!(said.contains("rank 1 of 2 was killed (signal: 9 (SIGKILL))"), "{said}");
            assert!(said.contains("all-reduce on rank 0 of 2 failed: rank 1 is gone"), "{said}");
            assert!(took < Duration::from_secs(timeout), "{took:?}: the survivor waited for its timeout");
        } else {
            assert!(said.contains(&format!("rank 1 did not answer within the timeout of {timeout}s")), "{said}");
            assert!(said.contains("rank(s) [1] were killed"), "{said}");
        }
        assert!(
            !Path::new(&format!("/proc/{}", victim[0])).exists()
                || std::fs::read_to_string(format!("/proc/{}/stat", victim[0])).is_ok_and(|s| s.contains(") Z ")),
            "SIG{signal}: rank 1 still alive"
        );
        let newest = common::checkpoint_names(&run).last().cloned().unwrap();
        let out = bin().arg("--resume").arg(&run).args(["--steps", "1", "--quiet"]).output().unwrap();
        let resumed = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "SIG{signal}: resuming {newest}: {}", String::from_utf8_lossy(&out.stderr));
        let step: i64 = newest.trim_start_matches("step-").trim_end_matches(".safetensors").parse().unwrap();
        assert!(resumed.contains(&format!("at step {step}/")), "SIG{signal}: not resumed from {newest}: {resumed}");
    }
}

/// A NaN injected into the generator's loss of step 2 on rank 1 alone makes both ranks
/// skip that update: rank 0 logs the skip, no other step is skipped, and the losses go on
/// as in one process that skips step 2 (a rank that had applied the NaN would have
/// poisoned every later average).
#[test]
fn a_non_finite_step_on_one_rank_is_skipped_on_both() {
    let _one = ONE_GROUP_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = TempDir::new("cli-nproc-nan").unwrap();
    let base = common::tiny_two_rank_config(&dir.0, 5);
    let configs = [("one-rank", "[1]"), ("every-rank", "[]")].map(|(name, ranks)| {
        let path = dir.path(&format!("{name}.toml"));
        let text = format!("{base}\n[debug]\ninject_nonfinite_steps = [2]\ninject_nonfinite_ranks = {ranks}\n");
        std::fs::write(&path, text).unwrap();
        path
    });
    let run = dir.path("ranks");
    let out = two_ranks(120).arg("--config").arg(&configs[0]).arg("--run-dir").arg(&run).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let alone = dir.path("alone");
    let out = bin().arg("--config").arg(&configs[1]).arg("--run-dir").arg(&alone).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let lines = |run: &Path| -> Vec<serde_json::Value> {
        let text = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
        text.lines().map(|l| serde_json::from_str(l).unwrap()).collect()
    };
    let (got, want) = (lines(&run), lines(&alone));
    assert_eq!(got.len(), 5);
    for (g, w) in got.iter().zip(&want) {
        let step = g["step"].as_i64().unwrap();
        assert_eq!(g["g_skipped"], serde_json::Value::Bool(step == 2), "step {step}: {g}");
        assert_eq!(g["g_skipped"], w["g_skipped"], "step {step}");
        assert_eq!(g["d_skipped"], serde_json::Value::Bool(false), "step {step}: {g}");
        for key in ["d_total", "g_total"] {
            let (a, b) = (w[key].as_f64(), g[key].as_f64());
            match (a, b) {
                (Some(a), Some(b)) => {
                    assert!((a - b).abs() <= 1e-4 * a.abs().max(1.0), "step {step} {key}: {a} alone, {b} as two ranks")
                }
                // A NaN is written as null; only the skipped step's generator total is one.
                _ => assert!(step == 2 && key == "g_total" && a.is_none() && b.is_none(), "step {step} {key}: {w} {g}"),
            }
        }
    }
}

/// `configs/chairs-tiny.toml` trains as two ranks (`--nproc 2`), through both of its stages:
/// the stage switch is moved to step 1, every step logged and the dataset cut to 64
/// images, nothing else.
#[test]
fn chairs_tiny_trains_as_two_ranks_through_both_stages() {
    let _one = ONE_GROUP_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = TempDir::new("cli-nproc-tiny").unwrap();
    let text = std::fs::read_to_string(common::repo_root().join("configs/chairs-tiny.toml")).unwrap();
    let edited = text
        .replace("path = \"../data/chairs-64\"", "path = \"data\"")
        .replace("count = 10000", "count = 64")
        .replace("from_step = 8000", "from_step = 1")
        .replace("log_interval = 10\n", "log_interval = 1\n");
    assert_eq!(edited.matches("path = \"data\"").count() + edited.matches("count = 64").count(), 2, "{edited}");
    assert!(edited.contains("from_step = 1\n") && edited.contains("log_interval = 1\n"), "{edited}");
    let cfg = dir.path("chairs-tiny.toml");
    std::fs::write(&cfg, edited).unwrap();
    let run = dir.path("run");
    let out =
        two_ranks(300).arg("--config").arg(&cfg).arg("--run-dir").arg(&run).args(["--steps", "2"]).output().unwrap();
    let said = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{said}");
    let text = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    let lines: Vec<serde_json::Value> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let seen: Vec<(i64, i64, i64)> = lines
        .iter()
        .map(|l| (l["step"].as_i64().unwrap(), l["resolution"].as_i64().unwrap(), l["batch_size"].as_i64().unwrap()))
        .collect();
    assert_eq!(seen, [(0, 32, 8), (1, 64, 4)], "{text}");
    for l in &lines {
        assert_eq!((l["d_skipped"].as_bool(), l["g_skipped"].as_bool()), (Some(false), Some(false)), "{l}");
    }
}
