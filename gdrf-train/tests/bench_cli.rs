//! `gdrf-bench allreduce` and `gdrf-bench step --nproc 2` end to end at a small size: they
//! start their ranks, join them through the c10d bridge, run the torch.distributed
//! reference, and write their JSON and plot.
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

/// `gdrf-bench step --nproc 2` on a tiny config: one process of 2 threads, 2 ranks of one,
/// and the reference both ways, each with its step and all-reduce times; the JSON and the
/// plot are written.
#[test]
fn step_scaling_runs_ranks_of_both_implementations() {
    let dir = common::TempDir::new("bench-step-nproc").unwrap();
    let cfg = dir.path("tiny.toml");
    std::fs::write(&cfg, common::tiny_two_rank_config(&dir.0, 10)).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_gdrf-bench"))
        .current_dir(common::repo_root())
        .args(["step", "--nproc", "2", "--steps", "2", "--warmup", "1", "--config"])
        .arg(&cfg)
        .arg("--out-dir")
        .arg(&dir.0)
        .output()
        .unwrap();
    let said = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{said}");
    assert!(said.contains("scaling efficiency"), "{said}");
    let doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path("step-tiny-stage0-b4-nproc2.json")).unwrap()).unwrap();
    assert_eq!(doc["phases"], serde_json::json!(["step", "allreduce"]));
    let runs = doc["runs"].as_array().unwrap();
    let names: Vec<&str> = runs.iter().map(|r| r["implementation"].as_str().unwrap()).collect();
    assert_eq!(
        names,
        [
            "gdrf, 1 process × 2 threads",
            "gdrf, 2 ranks × 1 thread",
            "PyTorch reference, 1 process × 2 threads",
            "PyTorch reference (torch.distributed), 2 ranks × 1 thread"
        ]
    );
    for (i, r) in runs.iter().enumerate() {
        let (step, comm) = (r["median_s"]["step"].as_f64().unwrap(), r["median_s"]["allreduce"].as_f64().unwrap());
        assert!(step > 0.0 && step.is_finite(), "{r}");
        // One process all-reduces nothing; ranks do.
        if i % 2 == 0 {
            assert_eq!(comm, 0.0, "{r}");
        } else {
            assert!(comm > 0.0 && comm < step, "{r}");
        }
        assert!(r["images_per_second"].as_f64().unwrap() > 0.0, "{r}");
    }
    assert!(dir.path("step-tiny-stage0-b4-nproc2.png").is_file());
}
