//! The load test of `gdrf-edit serve`: 8 simulated users (each its own page: orbiting, and
//! every fourth request another appearance) for 60 s against a server on 127.0.0.1, through
//! `gdrf-edit serve-bench --load-only`, which stops by itself. It asserts no error and the
//! server's peak memory under a stated bound (its caches are bounded: 32 grids, 256 feature
//! sets, one shape side, besides the generator and the inversion thread's copy of it), and
//! asserts nothing of latency. The report stays in the test's temporary folder; with
//! GDRF_LOAD_REPORT=FILE it is also copied there (docs/bench/serve-load.json is one).
#[path = "../../gdrf-core/tests/common/mod.rs"]
mod common;

use common::TempDir;
use std::process::Command;

/// The server's peak resident memory allowed, in MB (804 MB measured at 64² on the shipped
/// model: docs/bench/serve-load.json).
const PEAK_MB: f64 = 2048.0;

#[test]
fn eight_users_for_a_minute_meet_no_error_within_the_memory_bound() {
    let dir = TempDir::new("serve-load").unwrap();
    let stem = dir.path("load");
    let o = Command::new(env!("CARGO_BIN_EXE_gdrf-edit"))
        .args(["serve-bench", "--load-only", "--users", "8", "--seconds", "60", "--out", stem.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}\n{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    let path = dir.path("load-load.json");
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    println!("{report:#}");
    assert_eq!(report["errors"], 0, "{report}");
    assert!(report["requests"].as_u64().unwrap() >= 8, "every user got at least one answer: {report}");
    let peak = report["peak_server_mb"].as_f64().unwrap();
    assert!(peak > 0.0 && peak < PEAK_MB, "the server's peak memory {peak} MB, bound {PEAK_MB} MB");
    if let Some(to) = std::env::var_os("GDRF_LOAD_REPORT") {
        std::fs::copy(&path, to).unwrap();
    }
}
