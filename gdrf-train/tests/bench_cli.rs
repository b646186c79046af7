//! `gdrf-bench allreduce` end to end at a small size: it starts its ranks, joins them
//! through the c10d bridge, runs the torch.distributed reference, and writes its JSON and
//! plot.
#[path = "../../gdrf-core/tests/common/mod.rs"]
mod common;

use std::process::Command;

#[test]
fn allreduce_runs_its_ranks_and_the_reference_and_writes_json_and_a_plot() {
    let dir = common::TempDir::new("bench-allreduce").unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_gdrf-bench"))
        .current_dir(common::repo_root())
        .args(["allreduce", "--bucket-kib", "64,4096", "--repeats", "2", "--warmup", "1", "--out-dir"])
        .arg(&dir.0)
        .output()
        .unwrap();
    let said = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{said}");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path("allreduce-2ranks.json")).unwrap()).unwrap();
    assert_eq!(report["world"], 2);
    assert_eq!(report["bucket_kib"], serde_json::json!([64, 4096]));
    assert!(report["tensors"].as_u64().unwrap() > 10 && report["bytes"].as_u64().unwrap() > 1_000_000, "{report}");
    for who in ["gdrf", "torch"] {
        let m = report[who]["median_ms"].as_array().unwrap();
        assert_eq!(m.len(), 2, "{who}: {report}");
        assert!(m.iter().all(|v| v.as_f64().is_some_and(|v| v > 0.0 && v.is_finite())), "{who}: {report}");
    }
    assert_eq!(report["ratio"].as_array().unwrap().len(), 2);
    let png = image::open(dir.path("allreduce-2ranks.png")).unwrap();
    assert_eq!((png.width(), png.height()), (520, 300));
}
