//! `gdrf-train eval train-probe` and `gdrf-train eval` on a small procedural dataset: the
//! probe beats the majority class on held-out images by a stated margin, and a random
//! generator's images are far from the real ones where real images are near each other.
mod common;

use common::TempDir;
use gdrf_core::checkpoint::{save_generator, Header};
use gdrf_core::{CameraConfig, Generator, GeneratorConfig};
use std::path::Path;
use std::process::Command;
use tch::{nn, Device};

fn gdrf_train(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_gdrf-train")).args(args).output().expect("gdrf-train runs");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "gdrf-train {args:?} failed:\n{text}");
    text
}

fn accuracy_line(text: &str, factor: &str) -> (f64, f64) {
    let line = text
        .lines()
        .find(|l| l.trim_start().starts_with(factor))
        .unwrap_or_else(|| panic!("no {factor} line in:\n{text}"));
    let nums: Vec<f64> =
        line.split(|c: char| !(c.is_ascii_digit() || c == '.')).filter_map(|s| s.parse().ok()).collect();
    (nums[0], nums[1])
}

#[test]
fn probe_learns_and_eval_is_calibrated() {
    let tmp = TempDir::new("eval-cli");
    let data = tmp.path("chairs");
    let d = data.to_str().unwrap();
    gdrf_train(&[
        "dataset",
        "synth",
        "--count",
        "800",
        "--resolution",
        "32",
        "--supersample",
        "1",
        "--held-out",
        "0.25",
        "--out",
        d,
    ]);

    let probe = tmp.path("probe.safetensors");
    let text = gdrf_train(&[
        "eval",
        "train-probe",
        "--dataset",
        d,
        "--backbone",
        "scratch",
        "--epochs",
        "12",
        "--out",
        probe.to_str().unwrap(),
        "--threads",
        "2",
    ]);
    println!("{text}");
    // Legs (5 kinds) and back (5 kinds) are what topology coverage rests on: each must
    // beat always answering the most frequent class by at least 15 points.
    for factor in ["legs", "back"] {
        let (acc, chance) = accuracy_line(&text, factor);
        assert!(acc >= chance + 0.15, "{factor}: held-out accuracy {acc} vs majority class {chance}");
    }

    // A random-weight generator, scored against the dataset: the real-data end must be
    // far nearer the held-out images than the random generator is.
    let vs = nn::VarStore::new(Device::Cpu);
    let cfg = GeneratorConfig { latent_dim: 16, hidden_dim: 16, mapping_hidden_dim: 16, ..Default::default() };
    gdrf_core::rng::with_global_seed(0, || Generator::new(&vs.root(), &cfg).unwrap());
    let gen = tmp.path("random.safetensors");
    save_generator(&gen, &vs, &Header::generator(cfg, Some(CameraConfig::chair()))).unwrap();
    let out = tmp.path("eval");
    let text = gdrf_train(&[
        "eval",
        "--generator",
        gen.to_str().unwrap(),
        "--dataset",
        d,
        "--probe",
        probe.to_str().unwrap(),
        "--num",
        "48",
        "--swap",
        "3",
        "--steps",
        "6",
        "--real-resolution",
        "8",
        "--out",
        out.to_str().unwrap(),
        "--threads",
        "2",
    ]);
    println!("{text}");
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("eval.json")).unwrap()).unwrap();
    let fd = |end: &str| json["frechet"][end].as_f64().unwrap();
    assert!(fd("real") * 3.0 < fd("random"), "Fréchet real {} vs random {}", fd("real"), fd("random"));
    let kid = |end: &str| json["kernel"][end].as_f64().unwrap();
    assert!(kid("real") * 3.0 < kid("random"), "kernel real {} vs random {}", kid("real"), kid("random"));
    // 48 samples of 1280-d features: the covariances are singular and the report says so.
    assert!(json["warnings"][0].as_str().unwrap().contains("singular"));
    // The dataset's own swaps follow shape and appearance as constructed.
    assert!(json["shape_follows"]["real"].as_f64().unwrap() > 0.6, "{}", json["shape_follows"]);
    assert_eq!(json["classes"].as_array().unwrap().len(), 4);
    // The yaw error in each distribution's own frame is a minimum over rotations that
    // include none: never above the plain error; each rotation lies in [−180°, 180°).
    for end in ["model", "real", "random"] {
        let (plain, in_frame) = (
            json["pose_yaw_error_deg"][end].as_f64().unwrap(),
            json["pose_yaw_error_in_frame_deg"][end].as_f64().unwrap(),
        );
        assert!(in_frame <= plain, "{end}: in frame {in_frame} > plain {plain}");
        let offset = json["yaw_frame_offset_deg"][end].as_f64().unwrap();
        assert!((-180.0..180.0).contains(&offset), "{end}: rotation {offset}");
    }
    assert!(text.contains("in its own frame"), "{text}");
    // The real images seen at 8² instead of 32²: scored like the real end, and further from
    // the held-out images than the real end at full resolution.
    let low = &json["real_at_resolution"];
    assert_eq!(low["resolution"].as_i64(), Some(8), "{low}");
    for key in ["frechet", "kernel", "coverage_tv", "shape_follows", "appearance_follows", "pose_pitch_error_deg"] {
        assert!(low[key].as_f64().is_some_and(f64::is_finite), "{key}: {low}");
    }
    assert!(low["frechet"].as_f64().unwrap() > fd("real"), "at 8²: {low}, real end {}", fd("real"));
    assert!(text.contains("real images at 8²"), "{text}");
    assert!(Path::new(&out.join("report.png")).is_file());
    // A lower resolution that is not lower is refused, naming the flag.
    let bad = Command::new(env!("CARGO_BIN_EXE_gdrf-train"))
        .args(["eval", "--generator", gen.to_str().unwrap(), "--dataset", d, "--probe", probe.to_str().unwrap()])
        .args(["--real-resolution", "32", "--out", tmp.path("bad").to_str().unwrap()])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(!bad.status.success() && err.contains("--real-resolution 32"), "{err}");
    let img = image::open(out.join("report.png")).unwrap();
    assert!(img.width() >= 300 && img.height() >= 300);

    // Training scores its EMA generator every eval.interval steps into metrics.jsonl.
    let config = common::tiny_training_toml(
        "seed = 1\nthreads = 2",
        "total_steps = 2\nlog_interval = 1\ncheckpoint_interval = 1000\nsample_interval = 0",
        &format!(
            "[eval]\ninterval = 2\nnum = 8\nswap = 2\nsteps = 4\nprobe = {:?}\n\n[[stages]]\nfrom_step = 0\nresolution = 8\nnum_steps = 4\nbatch_size = 2\n\n[data]\npath = {:?}\n",
            probe.to_str().unwrap(),
            d
        ),
    );
    let cfg = tmp.path("tiny.toml");
    std::fs::write(&cfg, config).unwrap();
    let run = tmp.path("run");
    gdrf_train(&["--config", cfg.to_str().unwrap(), "--run-dir", run.to_str().unwrap(), "--quiet"]);
    let metrics = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    let evals: Vec<serde_json::Value> = metrics
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .filter(|v| v["event"] == "eval")
        .collect();
    assert_eq!(evals.len(), 1, "{metrics}");
    assert_eq!(evals[0]["step"], 2);
    assert!(evals[0]["frechet"].as_f64().unwrap() > 0.0);
    assert!(evals[0]["real_end"]["frechet"].as_f64().unwrap() > 0.0);
    assert!(evals[0]["coverage_tv"].as_f64().is_some());
    for e in [&evals[0], &evals[0]["real_end"]] {
        let (plain, in_frame) =
            (e["pose_yaw_error_deg"].as_f64().unwrap(), e["pose_yaw_error_in_frame_deg"].as_f64().unwrap());
        assert!(in_frame <= plain, "in frame {in_frame} > plain {plain}: {e}");
        assert!((-180.0..180.0).contains(&e["yaw_frame_offset_deg"].as_f64().unwrap()), "{e}");
    }
}

#[test]
fn eval_errors_name_what_is_missing() {
    let out =
        Command::new(env!("CARGO_BIN_EXE_gdrf-train")).args(["eval", "--generator", "g.safetensors"]).output().unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--dataset") && err.contains("--probe"), "{err}");
    let out = Command::new(env!("CARGO_BIN_EXE_gdrf-train"))
        .args(["eval", "train-probe", "--dataset", "no/such/dataset", "--backbone", "scratch"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("no/such/dataset"), "{err}");
    let out = Command::new(env!("CARGO_BIN_EXE_gdrf-train"))
        .args(["eval", "train-probe", "--dataset", "x", "--backbone", "resnet"])
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&out.stderr).contains("expected efficientnet or scratch"));
}
