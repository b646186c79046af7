//! `gdrf-train eval train-probe` and `gdrf-train eval` on a small procedural dataset: the
//! probe beats the majority class on held-out images by a stated margin, and a random
//! generator's images are far from the real ones where real images are near each other.
#[path = "../../gdrf-core/tests/common/mod.rs"]
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

/// Every number in `a` equals the one at the same place in `b` to float32 accuracy
/// (|a − b| ≤ 1e-9 + 1e-5·|b|; the features are float32), nulls (NaN) and the rest exactly.
fn assert_same_numbers(a: &serde_json::Value, b: &serde_json::Value, at: &str) {
    use serde_json::Value;
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => {
            let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
            assert!((x - y).abs() <= 1e-9 + 1e-5 * y.abs(), "{at}: {x} against {y}");
        }
        (Value::Object(x), Value::Object(y)) => {
            assert_eq!(x.keys().collect::<Vec<_>>(), y.keys().collect::<Vec<_>>(), "{at}");
            for (k, v) in x {
                assert_same_numbers(v, &y[k], &format!("{at}.{k}"));
            }
        }
        _ => assert_eq!(a, b, "{at}"),
    }
}

#[test]
fn probe_learns_and_eval_is_calibrated() {
    let tmp = TempDir::new("eval-cli").unwrap();
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
    let cfg = GeneratorConfig { latent_dim: 16, ..GeneratorConfig::tiny() };
    gdrf_core::rng::with_global_seed(0, || Generator::new(&vs.root(), &cfg).unwrap());
    let gen = tmp.path("random.safetensors");
    save_generator(&gen, &vs, &Header::generator(cfg, Some(CameraConfig::chair()))).unwrap();
    let out = tmp.path("eval");
    let (gen_arg, probe_arg) = (gen.to_str().unwrap(), probe.to_str().unwrap());
    let eval_args = |more: &[&str], out: &Path| -> Vec<String> {
        let mut v = vec!["eval", "--generator", gen_arg, "--dataset", d, "--probe", probe_arg];
        v.extend(["--num", "48", "--swap", "3", "--steps", "6", "--real-resolution", "8", "--threads", "2"]);
        v.extend(more);
        v.extend(["--out", out.to_str().unwrap()]);
        v.into_iter().map(String::from).collect()
    };
    let text = gdrf_train(&eval_args(&[], &out).iter().map(String::as_str).collect::<Vec<_>>());
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

    // Truncation to ψ = 0 renders every code as the mean code: each swap row is one image
    // repeated, so structure always follows the row (1 exactly) and colour never follows the
    // column (0 exactly) wherever a pair is counted. Only the model is truncated: both ends
    // repeat the untruncated run's.
    assert_eq!(json["psi"].as_f64(), Some(1.0));
    let trunc_out = tmp.path("eval-psi0");
    let text = gdrf_train(&eval_args(&["--psi", "0"], &trunc_out).iter().map(String::as_str).collect::<Vec<_>>());
    assert!(text.contains("model truncated to ψ = 0"), "{text}");
    let t: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(trunc_out.join("eval.json")).unwrap()).unwrap();
    assert_eq!(t["psi"].as_f64(), Some(0.0));
    for key in ["frechet", "kernel", "coverage_tv", "pose_yaw_error_deg", "pose_pitch_error_deg"] {
        for end in ["real", "random"] {
            assert_same_numbers(&t[key][end], &json[key][end], &format!("{key}.{end}"));
        }
    }
    assert_ne!(t["frechet"]["model"], json["frechet"]["model"]);
    assert!(matches!(t["shape_follows"]["model"].as_f64(), None | Some(1.0)), "{}", t["shape_follows"]);
    assert!(matches!(t["appearance_follows"]["model"].as_f64(), None | Some(0.0)), "{}", t["appearance_follows"]);
    for bad in ["--psi=-0.5", "--psi=NaN"] {
        let out = Command::new(env!("CARGO_BIN_EXE_gdrf-train"))
            .args(["eval", "--generator", gen_arg, "--dataset", d, "--probe", probe_arg, bad])
            .args(["--out", tmp.path("bad-psi").to_str().unwrap()])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && err.contains("--psi") && err.contains("≥ 0"), "{bad}: {err}");
    }

    // Several seeds share one real end, and each seed's result is exactly what a run with
    // that seed alone writes (the real end's kernel distance redrawn with each seed's subsets).
    // This run names the samples per ray `--samples`, gdrf-invert's name for them, and must
    // score seed 0 exactly as the first run did with `--steps`.
    let multi = tmp.path("eval-seeds");
    let args: Vec<String> = eval_args(&["--seeds", "1,0"], &multi)
        .into_iter()
        .map(|a| if a == "--steps" { "--samples".to_string() } else { a })
        .collect();
    let text = gdrf_train(&args.iter().map(String::as_str).collect::<Vec<_>>());
    println!("{text}");
    let read = |p: &Path| serde_json::from_str::<serde_json::Value>(&std::fs::read_to_string(p).unwrap()).unwrap();
    let (s0, s1) = (read(&multi.join("seed-0/eval.json")), read(&multi.join("seed-1/eval.json")));
    let keys = [
        "frechet",
        "kernel",
        "coverage_tv",
        "shape_follows",
        "appearance_follows",
        "pose_yaw_error_deg",
        "pose_yaw_error_in_frame_deg",
        "pose_pitch_error_deg",
    ];
    for key in keys.iter().chain(&["real_at_resolution"]) {
        assert_same_numbers(&s0[key], &json[key], key);
    }
    assert_eq!((s0["seed"].as_u64(), s1["seed"].as_u64()), (Some(0), Some(1)));
    // Another seed draws another random generator: its random end differs.
    assert_ne!(s1["frechet"]["random"], s0["frechet"]["random"]);
    assert!(multi.join("seed-1/report.png").is_file());
    let spread = read(&multi.join("seeds.json"));
    assert_eq!(spread["seeds"], serde_json::json!([1, 0]));
    let scores = spread["scores"].as_array().unwrap();
    assert_eq!(scores.len(), keys.len());
    for (row, key) in scores.iter().zip(keys) {
        // NaN (a score without informative pairs, or an end without span) is null in JSON;
        // the means count the seeds whose model, real and random values are all finite.
        let v = |j: &serde_json::Value, end: &str| j[key][end].as_f64();
        let triple = |j: &serde_json::Value| Some((v(j, "model")?, v(j, "real")?, v(j, "random")?));
        let counted: Vec<(f64, f64, f64)> = [&s1, &s0].into_iter().filter_map(triple).collect();
        assert_eq!(row["counted"].as_u64(), Some(counted.len() as u64), "{key}: {row}");
        let n = counted.len() as f64;
        let mean_of = |f: fn(&(f64, f64, f64)) -> f64| counted.iter().map(f).sum::<f64>() / n;
        if !counted.is_empty() {
            assert_eq!(row["mean"]["model"].as_f64().unwrap(), mean_of(|t| t.0), "{key}");
            assert_eq!(row["mean"]["random"].as_f64().unwrap(), mean_of(|t| t.2), "{key}");
        }
        if counted.len() == 2 {
            // Two values: the sample standard deviation is |a − b| / √2.
            let sd = row["model_sd"].as_f64().unwrap();
            let want = (counted[0].0 - counted[1].0).abs() / 2f64.sqrt();
            assert!((sd - want).abs() <= 1e-12 * (1.0 + want), "{key}: {sd} against {want}");
        }
        let positions: Vec<f64> = [&s1, &s0].into_iter().filter_map(|j| v(j, "position")).collect();
        if !positions.is_empty() {
            let worst = positions.iter().copied().fold(f64::INFINITY, f64::min);
            assert_eq!(row["worst_position"].as_f64().unwrap(), worst, "{key}");
        }
        assert_eq!(row["position"].as_array().unwrap().len(), 2, "{key}");
    }
    assert!(text.contains("seed 1") && text.contains("of means"), "{text}");
    // A seed listed twice, and --seed with --seeds, are refused by name.
    for (flags, expect) in [(vec!["--seeds", "2,2"], "--seeds"), (vec!["--seed", "1", "--seeds", "0,1"], "--seed")] {
        let bad = Command::new(env!("CARGO_BIN_EXE_gdrf-train"))
            .args(["eval", "--generator", gen.to_str().unwrap(), "--dataset", d, "--probe", probe.to_str().unwrap()])
            .args(&flags)
            .args(["--out", tmp.path("bad-seeds").to_str().unwrap()])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&bad.stderr);
        assert!(!bad.status.success() && err.contains(expect), "{flags:?}: {err}");
    }

    // Training scores its EMA generator every eval.interval steps onto the run's learning
    // curve, exactly as `gdrf-train eval --seeds` scores the checkpoint of that step.
    let config = common::tiny_training_toml(
        "seed = 1\nthreads = 2",
        "total_steps = 4\nlog_interval = 1\ncheckpoint_interval = 2\nkeep_checkpoints = 5\nsample_interval = 0",
        &format!(
            "[eval]\ninterval = 2\nnum = 8\nswap = 3\nsteps = 4\nresolution = 16\nseeds = [0, 3]\nprobe = {:?}\n\n[[stages]]\nfrom_step = 0\nresolution = 8\nnum_steps = 4\nbatch_size = 2\n\n[data]\npath = {:?}\n",
            probe.to_str().unwrap(),
            d
        ),
    );
    let cfg = tmp.path("tiny.toml");
    std::fs::write(&cfg, config).unwrap();
    let run = tmp.path("run");
    gdrf_train(&["--config", cfg.to_str().unwrap(), "--run-dir", run.to_str().unwrap(), "--quiet"]);
    let lines: Vec<serde_json::Value> = std::fs::read_to_string(run.join("curve.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.iter().map(|l| l["step"].as_i64().unwrap()).collect::<Vec<_>>(), [2, 4]);
    assert_eq!(lines[1]["images_seen"], 8);
    for l in &lines {
        assert_eq!(l["scores"]["seeds"], serde_json::json!([0, 3]));
        assert_eq!((l["scores"]["images"].as_i64(), l["scores"]["resolution"].as_i64()), (Some(8), Some(16)));
        assert!(l["step_seconds"].as_f64().unwrap() > 0.0 && l["eval_seconds"].as_f64().unwrap() > 0.0, "{l}");
        assert!(l["train_seconds"].as_f64().unwrap() > 0.0, "{l}");
    }
    assert!(lines[1]["train_seconds"].as_f64() > lines[0]["train_seconds"].as_f64());
    let metrics = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    assert!(!metrics.contains("\"eval\""), "the curve is the one record of the scores");
    // Step 2 from its training checkpoint, step 4 from the generator kept beside its scores.
    for step in [2, 4] {
        let ckpt = match step {
            2 => run.join("checkpoints/step-00000002.safetensors"),
            _ => run.join("evals/step-00000004/generator.safetensors"),
        };
        let out = tmp.path(&format!("curve-cli-{step}"));
        gdrf_train(&[
            "eval",
            "--generator",
            ckpt.to_str().unwrap(),
            "--dataset",
            d,
            "--probe",
            probe.to_str().unwrap(),
            "--num",
            "8",
            "--swap",
            "3",
            "--steps",
            "4",
            "--resolution",
            "16",
            "--seeds",
            "0,3",
            "--out",
            out.to_str().unwrap(),
        ]);
        let cli: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("seeds.json")).unwrap()).unwrap();
        let curve = &lines[step / 2 - 1]["scores"];
        assert_same_numbers(&curve["scores"], &cli["scores"], &format!("curve at step {step}"));
        // The evaluation's full record sits beside the curve, as the CLI writes it.
        let dir = run.join(format!("evals/step-{step:08}"));
        for f in ["seeds.json", "seed-0/eval.json", "seed-0/report.png", "seed-3/report.png", "frame.png"] {
            assert!(dir.join(f).is_file(), "{}", dir.join(f).display());
        }
    }
    // The plot: five panels of 520 × 320 in two columns and a caption; the filmstrip: a row
    // per evaluation, each 16 px samples (two rows of four) beside the swap matrix's 3 × 3.
    let plot = image::open(run.join("curve.png")).unwrap().to_rgb8();
    assert_eq!(plot.dimensions(), (1040, 3 * 320 + 22));
    let strip = image::open(run.join("filmstrip.png")).unwrap().to_rgb8();
    assert_eq!(strip.dimensions(), (96 + 4 * 16 + 8 + 3 * 16 + 6, 2 * (3 * 16 + 6) + 6));
    // `gdrf-train ship` copies the evaluation the rule ranks best, byte for byte.
    let lowest = |l: &serde_json::Value| {
        l["scores"]["scores"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|s| gdrf_core::train::curve::RULE_SCORES.contains(&s["score"].as_str().unwrap()))
            .filter_map(|s| s["mean"]["position"].as_f64())
            .fold(f64::INFINITY, f64::min)
    };
    // A four-step run is far from the goal, so the positions alone decide.
    assert!(lines.iter().all(|l| !gdrf_core::train::curve::meets_goal(l)), "a four-step run meets the goal?");
    let want = if lowest(&lines[0]) > lowest(&lines[1]) { 2 } else { 4 };
    let shipped = tmp.path("shipped");
    let said = gdrf_train(&["ship", run.to_str().unwrap(), "--out", shipped.to_str().unwrap()]);
    assert!(said.starts_with(&format!("step {want} of 2 evaluations: short of the goal")), "{said}");
    // With it, where the curve stands under the flatness rule (gdrf_core::train::plateau).
    assert!(said.contains("before its last evaluation (step 4): not flat"), "{said}");
    let evaluated = run.join(format!("evals/step-{want:08}"));
    for f in ["generator.safetensors", "seeds.json"] {
        let made = std::fs::read(shipped.join(f)).unwrap();
        assert_eq!(made, std::fs::read(evaluated.join(f)).unwrap(), "{f}");
    }
    // Without the evaluation folder's copies, the same generator comes from the step's
    // checkpoint, byte for byte, and the same scores from the curve.
    for f in ["generator.safetensors", "seeds.json"] {
        std::fs::rename(evaluated.join(f), tmp.path(&format!("kept-{f}"))).unwrap();
    }
    let again = tmp.path("shipped-from-checkpoint");
    let said = gdrf_train(&["ship", run.to_str().unwrap(), "--out", again.to_str().unwrap()]);
    assert!(said.contains(&format!("checkpoints/step-{want:08}.safetensors")), "{said}");
    let g = std::fs::read(again.join("generator.safetensors")).unwrap();
    assert_eq!(g, std::fs::read(shipped.join("generator.safetensors")).unwrap(), "generator from the checkpoint");
    let json = |p: &Path| serde_json::from_str::<serde_json::Value>(&std::fs::read_to_string(p).unwrap()).unwrap();
    assert_eq!(json(&again.join("seeds.json")), json(&shipped.join("seeds.json")));
    // Without the step's checkpoint either (a snapshot keeps only its newest), a folder that
    // already holds that step's export is left as it is; one holding another step's scores,
    // or nothing, is refused, naming what is missing.
    let checkpoint = run.join(format!("checkpoints/step-{want:08}.safetensors"));
    std::fs::rename(&checkpoint, tmp.path("kept-checkpoint")).unwrap();
    let held = [g.clone(), std::fs::read(again.join("seeds.json")).unwrap()];
    let said = gdrf_train(&["ship", run.to_str().unwrap(), "--out", again.to_str().unwrap()]);
    assert!(said.contains(&format!("step {want} of 2 evaluations")) && said.contains("unchanged"), "{said}");
    let now =
        [std::fs::read(again.join("generator.safetensors")).unwrap(), std::fs::read(again.join("seeds.json")).unwrap()];
    assert!(now == held, "an export already in place was rewritten");
    let other = tmp.path("shipped-other-step");
    std::fs::create_dir_all(&other).unwrap();
    std::fs::write(other.join("generator.safetensors"), &g).unwrap();
    let other_scores = &lines[if want == 2 { 1 } else { 0 }]["scores"];
    std::fs::write(other.join("seeds.json"), serde_json::to_string_pretty(other_scores).unwrap()).unwrap();
    for out in [&other, &tmp.path("shipped-nowhere")] {
        let refused = Command::new(env!("CARGO_BIN_EXE_gdrf-train"))
            .args(["ship", run.to_str().unwrap(), "--out", out.to_str().unwrap()])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&refused.stderr);
        assert!(
            !refused.status.success()
                && err.contains(checkpoint.to_str().unwrap())
                && err.contains(&format!("{} does not hold it already", out.display())),
            "{err}"
        );
    }
    assert!(!tmp.path("shipped-nowhere").exists(), "a refused ship left its --out behind");
    std::fs::rename(tmp.path("kept-checkpoint"), &checkpoint).unwrap();
    for f in ["generator.safetensors", "seeds.json"] {
        std::fs::rename(tmp.path(&format!("kept-{f}")), evaluated.join(f)).unwrap();
    }
    // Resumed from the step-2 checkpoint, the run drops the later evaluation and makes it
    // again, identically.
    std::fs::remove_file(run.join("checkpoints/step-00000004.safetensors")).unwrap();
    gdrf_train(&["--resume", run.to_str().unwrap(), "--quiet"]);
    let again: Vec<serde_json::Value> = std::fs::read_to_string(run.join("curve.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(again.len(), 2);
    assert_same_numbers(&again[1]["scores"]["scores"], &lines[1]["scores"]["scores"], "resumed curve");

    // `gdrf-train snapshot`: the newest checkpoint, the config, metrics and curve, and every
    // evaluation's filmstrip row, byte for byte, and nothing else.
    let snap = tmp.path("snapshot");
    let (r, s) = (run.to_str().unwrap(), snap.to_str().unwrap());
    let snapshot = |out: &str| {
        Command::new(env!("CARGO_BIN_EXE_gdrf-train")).args(["snapshot", r, "--out", out]).output().unwrap()
    };
    {
        // A run being trained (its lock held) is refused, naming it, and nothing is written.
        let _training = gdrf_core::train::run::RunLock::acquire(&run).unwrap();
        let refused = snapshot(s);
        let err = String::from_utf8_lossy(&refused.stderr);
        assert!(!refused.status.success() && err.contains(r) && err.contains("in use"), "{err}");
        assert!(!snap.exists());
    }
    let said = gdrf_train(&["snapshot", r, "--out", s]);
    assert!(said.contains("step 4") && said.contains("2 evaluation frames (8 files)"), "{said}");
    fn files_under(dir: &Path, base: &Path, out: &mut Vec<String>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                files_under(&p, base, out);
            } else {
                out.push(p.strip_prefix(base).unwrap().to_string_lossy().into_owned());
            }
        }
    }
    let listing = |dir: &Path| {
        let mut v = Vec::new();
        files_under(dir, dir, &mut v);
        v.sort();
        v
    };
    let copied = listing(&snap);
    assert_eq!(
        copied,
        [
            "checkpoints/step-00000004.safetensors",
            "config.toml",
            "curve.jsonl",
            "curve.png",
            "evals/step-00000002/frame.png",
            "evals/step-00000004/frame.png",
            "filmstrip.png",
            "metrics.jsonl"
        ]
    );
    for f in &copied {
        assert_eq!(std::fs::read(snap.join(f)).unwrap(), std::fs::read(run.join(f)).unwrap(), "{f}");
    }
    // The copy draws the same filmstrip again from its frames, as a run resumed from it does
    // at its next evaluation.
    std::fs::remove_file(snap.join("filmstrip.png")).unwrap();
    gdrf_train(&["plot", s]);
    let redrawn = std::fs::read(snap.join("filmstrip.png")).unwrap();
    assert_eq!(redrawn, std::fs::read(run.join("filmstrip.png")).unwrap(), "filmstrip re-drawn from the copy");
    // A stage that starts after the last improvement (here: after the first evaluation)
    // restarts the flatness rule's count from its step.
    let cfg = snap.join("config.toml");
    let mut text = std::fs::read_to_string(&cfg).unwrap();
    text.push_str("\n[[stages]]\nfrom_step = 3\nresolution = 8\nnum_steps = 4\nbatch_size = 2\nd_lr = 1e-4\n");
    std::fs::write(&cfg, text).unwrap();
    let said = gdrf_train(&["plot", s]);
    let want = if gdrf_core::train::plateau::verdicts(&lines)[1].improves.is_empty() {
        // Last improved at step 2 (the first evaluation): the stage at step 3 is later.
        "at step 2; a stage changed the schedule at step 3, and the rule counts from there, 1 steps before its last evaluation (step 4): not flat"
    } else {
        // Step 4 improved a score, which is later than the stage.
        "at step 4, 0 steps before its last evaluation (step 4): not flat"
    };
    assert!(said.contains(want), "{said}");
    // curve.png and losses.png mark the stage's start: step 3, after 3 steps of batch 2
    // (curve.jsonl counts the images of the steps done, as the stage's start does).
    let snap_cfg = gdrf_core::train::config::TrainConfig::load(&cfg).unwrap();
    let snap_metrics = gdrf_core::train::run::read_metrics(&snap).unwrap();
    assert_eq!(gdrf_core::train::curve::stage_starts(&snap_cfg, &snap_metrics), [(3, 6)]);
    // The filmstrip marks it too: the evaluation at step 2 came before the stage's first
    // step, the one at step 4 after it, so a dashed line (4 px on, 4 off, grey 150) runs
    // through the gap above the step-4 row (rows 48 px tall, 6 apart) and that row's label
    // names the stage in the space below its two lines. Nothing else changes.
    let plain = image::open(run.join("filmstrip.png")).unwrap().to_rgb8();
    let marked = image::open(snap.join("filmstrip.png")).unwrap().to_rgb8();
    assert_eq!(marked.dimensions(), plain.dimensions());
    let (gap_y, row_y) = (6 + 48 + 3, 6 + 48 + 6);
    let label = |x: u32, y: u32| x < 96 && (row_y + 26..row_y + 48).contains(&y);
    let white = image::Rgb([255u8; 3]);
    let mut inked = 0;
    for (x, y, &p) in marked.enumerate_pixels() {
        let was = *plain.get_pixel(x, y);
        if y == gap_y {
            assert_eq!(was, white, "({x}, {y}) unmarked");
            let dash = if x % 8 < 4 { image::Rgb([150u8; 3]) } else { white };
            assert_eq!(p, dash, "({x}, {y})");
        } else if label(x, y) {
            assert_eq!(was, white, "({x}, {y}) unmarked");
            inked += usize::from(p != white);
        } else {
            assert_eq!(p, was, "({x}, {y})");
        }
    }
    assert!(inked > 50, "the stage's label drew {inked} pixels");
    // A second snapshot replaces the first whole and leaves no temporary folder beside it;
    // it removes the one a killed snapshot left (4 194 305: above Linux's largest process id).
    std::fs::write(snap.join("stray.txt"), "from before").unwrap();
    std::fs::create_dir_all(tmp.path(".snapshot.tmp-4194305/checkpoints")).unwrap();
    gdrf_train(&["snapshot", r, "--out", s]);
    assert_eq!(listing(&snap), copied);
    let beside: Vec<_> = std::fs::read_dir(&tmp.0)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(".snapshot"))
        .collect();
    assert!(beside.is_empty(), "{beside:?}");
    // A copy without its frames still plots its curve and says where the curve stands.
    std::fs::remove_dir_all(snap.join("evals")).unwrap();
    std::fs::remove_file(snap.join("filmstrip.png")).unwrap();
    let said = gdrf_train(&["plot", s]);
    assert!(said.contains("no filmstrip") && said.contains("before its last evaluation (step 4)"), "{said}");
    assert!(!snap.join("filmstrip.png").exists());
    gdrf_train(&["snapshot", r, "--out", s]);
    // A folder that is neither empty nor a run (here the dataset), the run itself and a
    // folder holding it are refused by name and left as they were.
    for (out, expect) in [
        (d, "refusing to replace it"),
        (r, "must not hold one another"),
        (tmp.0.to_str().unwrap(), "must not hold one another"),
    ] {
        let refused = snapshot(out);
        let err = String::from_utf8_lossy(&refused.stderr);
        assert!(!refused.status.success() && err.contains(out) && err.contains(expect), "{out}: {err}");
    }
    assert!(data.join("metadata.json").is_file() && run.join("checkpoints/step-00000004.safetensors").is_file());
}

#[test]
fn eval_errors_name_what_is_missing() {
    // --checkpoint is --generator's other name, as in gdrf-edit and gdrf-invert.
    for flag in ["--generator", "--checkpoint"] {
        let out =
            Command::new(env!("CARGO_BIN_EXE_gdrf-train")).args(["eval", flag, "g.safetensors"]).output().unwrap();
        assert!(!out.status.success());
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains("--dataset") && err.contains("--probe"), "{flag}: {err}");
    }
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
