//! `gdrf-invert` from the command line: a run writes every output and its features reload
//! in gdrf-edit's format; every kind of bad input is an error that names it and leaves
//! nothing behind; the initialiser trains, is refused by another generator and starts an
//! inversion.
#[path = "../../gdrf-core/tests/common/mod.rs"]
mod common;

use common::TempDir;
use gdrf_core::checkpoint::{load_generator, save_generator};
use gdrf_core::data::synth::{encode_png, render_object, sample_object, Category, SynthOptions};
use gdrf_core::edit::{generator_id, Features};
use std::process::{Command, Output};
use tch::{Device, Kind};

fn gdrf_invert(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_gdrf-invert")).args(args).output().expect("gdrf-invert runs")
}

fn text(o: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

fn ok(args: &[&str]) -> String {
    let o = gdrf_invert(args);
    assert!(o.status.success(), "gdrf-invert {args:?} failed:\n{}", text(&o));
    text(&o)
}

fn as_args(v: &[String]) -> Vec<&str> {
    v.iter().map(String::as_str).collect()
}

fn fails(args: &[&str], wants: &[&str]) {
    let o = gdrf_invert(args);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "gdrf-invert {args:?} should fail:\n{t}");
    for w in wants {
        assert!(t.contains(w), "gdrf-invert {args:?}: expected '{w}' in:\n{t}");
    }
}

/// A procedural chair (a held-out kind of object: seed 123 456 is in no training set) at
/// pitch 62.5°, yaw −8.2°, 32×32, written as PNG into `dir`.
fn photo_in(dir: &TempDir) -> String {
    let opts = SynthOptions { resolution: 32, supersample: 1, shadows: false, ..Default::default() };
    let (shape, app) = sample_object(Category::Chairs, 123_456);
    let r = render_object(&shape, &app, 62.5f64.to_radians(), -8.2f64.to_radians(), &opts).unwrap();
    let rgba: Vec<u8> = r
        .rgb
        .chunks(3)
        .flat_map(|c| [c[0], c[1], c[2]].map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).into_iter().chain([255]))
        .collect();
    let path = dir.path("chair.png");
    std::fs::write(&path, encode_png(rgba, 32).unwrap()).unwrap();
    path.display().to_string()
}

/// A small procedural dataset (12 images at 16², half held out) in `dir`: its held-out
/// objects are what `gdrf-invert bench` inverts.
fn bench_dataset(dir: &TempDir) -> std::path::PathBuf {
    let data = dir.path("chairs");
    let opts = SynthOptions {
        count: 12,
        resolution: 16,
        supersample: 1,
        held_out_fraction: 0.5,
        shadows: false,
        ..Default::default()
    };
    gdrf_core::data::synth::generate(&data, &opts, 2, &|| {}).unwrap();
    data
}

#[test]
fn a_photo_inverts_and_bad_inputs_are_named() {
    let tmp = TempDir::new("invert-cli").unwrap();
    let photo = photo_in(&tmp);
    let out = tmp.path("out");
    let o = out.to_str().unwrap();
    let small = ["--steps", "3", "--resolution", "16", "--samples", "4", "--orbit", "2", "--quiet"];
    let mut args = vec![photo.as_str(), "--pose", "62.5,-8.2", "--out", o];
    args.extend(small);
    let said = ok(&args);
    assert!(said.contains("reconstruction PSNR"), "{said}");
    for f in [
        "features.safetensors",
        "input.png",
        "reconstruction.png",
        "compare.png",
        "orbit.gif",
        "orbit/frame-001.png",
        "loss.png",
        "invert.json",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("invert.json")).unwrap()).unwrap();
    assert_eq!(report["steps_run"], 3);
    assert!(report["perceptual"].as_str().unwrap().contains("not LPIPS"));
    let m = load_generator(&gdrf_core::paths::shipped_generator(), Device::Cpu, Kind::Float).unwrap();
    let f =
        Features::load(&out.join("features.safetensors"), &m.generator, &generator_id(&m.vs, &m.generator)).unwrap();
    let p = f.pose.unwrap();
    assert!((p.0.to_degrees() - 62.5).abs() < 1e-9 && (p.1.to_degrees() + 8.2).abs() < 1e-9);
    assert_eq!(report["camera"]["fov_deg"], 50.0, "the generator's own camera");

    // --camera takes a preset instead of the generator's camera (as in gdrf-edit): without
    // --pose the photo starts at that camera's mean pose (car: pitch 1.2217 rad, yaw 0).
    let car = tmp.path("car");
    let mut args = vec![photo.as_str(), "--camera", "car", "--out", car.to_str().unwrap()];
    args.extend(small);
    ok(&args);
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(car.join("invert.json")).unwrap()).unwrap();
    assert_eq!(report["camera"]["fov_deg"], 30.0);
    let start = &report["start_pose_deg"];
    assert!((start[0].as_f64().unwrap() - 1.2217f64.to_degrees()).abs() < 1e-9, "{start}");
    assert_eq!(start[1].as_f64(), Some(0.0), "{start}");

    // Without --resolution and --samples it inverts where the generator learned (the shipped
    // header: 32², 24 samples per ray, so 12 + 12); a generator without that record gets 64²
    // and 24 + 24, and a flag given wins over the header.
    let bare = tmp.path("bare.safetensors");
    let mut header = m.header.clone();
    header.info.clear();
    save_generator(&bare, &m.vs, &header).unwrap();
    let config_of = |extra: &[&str], name: &str| -> (i64, i64, String) {
        let dir = tmp.path(name);
        let mut args = vec![photo.as_str(), "--pose", "62.5,-8.2", "--steps", "1", "--orbit", "0", "--quiet"];
        args.extend(["--out", dir.to_str().unwrap()]);
        args.extend(extra);
        let said = ok(&args);
        let r: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join("invert.json")).unwrap()).unwrap();
        (r["config"]["resolution"].as_i64().unwrap(), r["config"]["samples"].as_i64().unwrap(), said)
    };
    let (res, n, said) = config_of(&[], "learned");
    assert_eq!((res, n), (32, 12));
    assert!(said.contains("at 32² (where the generator learned) with 12 + 12 samples"), "{said}");
    let (res, n, said) = config_of(&["--generator", bare.to_str().unwrap()], "bare");
    assert_eq!((res, n), (64, 24));
    assert!(!said.contains("where the generator learned"), "{said}");
    let (res, n, _) = config_of(&["--resolution", "16", "--samples", "4"], "given");
    assert_eq!((res, n), (16, 4));

    // --grid takes gdrf-edit's values. `auto` counts the samples one grid serves: 10 steps
    // (--grid-refresh) × 32² pixels × 24 samples = 245 760, over 100 000, so a 32³ grid
    // sampled only in its cells; refreshed every 3 steps, 73 728, so none. Off by default.
    let grid_of = |extra: &[&str], name: &str| -> (i64, bool) {
        let dir = tmp.path(name);
        let mut args = vec![photo.as_str(), "--pose", "62.5,-8.2", "--steps", "2", "--orbit", "0", "--quiet"];
        args.extend(["--out", dir.to_str().unwrap()]);
        args.extend(extra);
        ok(&args);
        let r: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join("invert.json")).unwrap()).unwrap();
        (r["config"]["grid"].as_i64().unwrap(), r["config"]["grid_cells"].as_bool().unwrap())
    };
    assert_eq!(grid_of(&[], "grid-default"), (0, false));
    assert_eq!(grid_of(&["--grid", "auto"], "grid-auto"), (32, true));
    assert_eq!(grid_of(&["--grid", "auto", "--grid-refresh", "3"], "grid-auto-3"), (0, false));
    assert_eq!(grid_of(&["--grid", "16"], "grid-16"), (16, false));
    assert_eq!(grid_of(&["--grid", "16", "--grid-cells"], "grid-16-cells"), (16, true));

    // Bad inputs: each named, and the output folder is never created for them.
    let fresh = tmp.path("never");
    let n = fresh.to_str().unwrap();
    std::fs::write(tmp.path("junk.png"), b"not a png").unwrap();
    std::fs::write(tmp.path("empty.jpg"), b"").unwrap();
    let junk = tmp.path("junk.png").display().to_string();
    let empty = tmp.path("empty.jpg").display().to_string();
    fails(&["missing.png", "--out", n], &["missing.png", "no such file"]);
    fails(&[&junk, "--out", n], &["junk.png", "not a PNG or JPEG"]);
    fails(&[&empty, "--out", n], &["empty.jpg", "empty file"]);
    fails(&[&photo, "--pose", "sixty", "--out", n], &["--pose", "PITCH,YAW"]);
    fails(&[&photo, "--mask", &junk, "--out", n], &["mask", "junk.png"]);
    fails(&[&photo, "--steps", "3", "--lr=-1", "--out", n], &["invert.lr"]);
    fails(&[&photo, "--refine-pose", "--pose-lr", "0", "--out", n], &["--pose-lr", "degrees"]);
    fails(&[&photo, "--generator", &junk, "--out", n], &["--generator", "junk.png"]);
    // A value clap refuses (exit status 2, as for any malformed flag), naming the flag.
    let refused = gdrf_invert(&[&photo, "--grid", "2", "--out", n]);
    let t = text(&refused);
    assert_eq!(refused.status.code(), Some(2), "{t}");
    assert!(t.contains("'2' for '--grid <GRID>'") && t.contains("expected auto, off (or 0)"), "{t}");
    fails(&[&photo, "--grid-cells", "--out", n], &["--grid-cells", "--grid"]);
    assert!(!fresh.exists(), "a failed run created its output folder");
    // An output folder that holds files is refused without --force.
    fails(&[&photo, "--out", o], &["--force"]);
}

#[test]
fn the_initialiser_trains_refuses_another_generator_and_starts_an_inversion() {
    let tmp = TempDir::new("invert-cli-init").unwrap();
    let photo = photo_in(&tmp);
    let init = tmp.path("init.safetensors");
    let i = init.to_str().unwrap();
    // A small initialiser run: 24 tuples (8 held out) at 16², validation every 2 steps.
    let small = |steps: &'static str, extra: &[&'static str]| -> Vec<String> {
        let mut v = vec!["train-init", "--out", i, "--count", "24", "--held-out", "8", "--steps", steps];
        v.extend(["--eval-interval", "2", "--resolution", "16", "--samples", "4", "--batch-size", "8", "--quiet"]);
        v.extend(extra);
        v.into_iter().map(String::from).collect()
    };
    let said = ok(&as_args(&small("4", &[])));
    // Each validation is reported as it happens, also when the output is not a terminal.
    for step in [2, 4] {
        assert!(said.contains(&format!("step {step}: held-out w_s MSE")), "{said}");
    }
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(tmp.path("init.safetensors.json")).unwrap()).unwrap();
    assert_eq!(report["evaluations"].as_array().unwrap().len(), 2);
    // Not overwritten without --resume; --resume continues to a longer run.
    fails(&["train-init", "--out", i, "--count", "24", "--held-out", "8", "--steps", "6"], &["--resume"]);
    ok(&as_args(&small("6", &["--resume"])));

    // Another generator (one weight changed) refuses this initialiser, naming both.
    let mut m = load_generator(&gdrf_core::paths::shipped_generator(), Device::Cpu, Kind::Float).unwrap();
    tch::no_grad(|| {
        let mut w = m.vs.variables()["deform.head.bias"].shallow_clone();
        let _ = w.g_add_scalar_(0.01);
    });
    let other = tmp.path("other.safetensors");
    save_generator(&other, &m.vs, &m.header).unwrap();
    let _ = &mut m;
    let out = tmp.path("inv");
    fails(
        &[&photo, "--generator", other.to_str().unwrap(), "--init", i, "--out", out.to_str().unwrap()],
        &["--init", "trained for generator"],
    );
    // With the right generator the initialiser gives the start and the pose.
    let said = ok(&[
        &photo,
        "--init",
        i,
        "--steps",
        "2",
        "--resolution",
        "16",
        "--samples",
        "4",
        "--orbit",
        "0",
        "--out",
        out.to_str().unwrap(),
        "--quiet",
    ]);
    assert!(said.contains("2 steps"), "{said}");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("invert.json")).unwrap()).unwrap();
    assert!(report["init"].as_str().unwrap().ends_with("init.safetensors"));

    // The bench with this initialiser: ten methods, each starting from its prediction but
    // one (the mean code, for comparison), and the file named in the JSON.
    let data = bench_dataset(&tmp);
    let stem = tmp.path("bench");
    let d = data.to_str().unwrap();
    let s = stem.to_str().unwrap();
    let small = ["--images", "1", "--views", "1", "--reference-steps", "4", "--steps", "2", "--resolution", "16"];
    let mut args = vec!["bench", "--init", i, "--dataset", d, "--samples", "4", "--out", s];
    args.extend(small);
    ok(&args);
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(stem.with_extension("json")).unwrap()).unwrap();
    assert_eq!(json["init"].as_str(), Some(i));
    let mut methods: Vec<&str> =
        json["points"].as_array().unwrap().iter().map(|p| p["method"].as_str().unwrap()).collect();
    methods.dedup();
    assert_eq!(methods.len(), 13, "{methods:?}");
    assert_eq!(methods.iter().filter(|m| m.starts_with("mean code")).count(), 1, "{methods:?}");
    for angle in ["pitch", "yaw"] {
        let e = json["initialiser_pose_error_deg"][angle].as_f64().unwrap();
        assert!((0.0..=180.0).contains(&e), "{angle} error {e}");
    }
}

#[test]
fn the_bench_scores_every_method_from_one_start_and_writes_its_outputs() {
    let tmp = TempDir::new("invert-bench").unwrap();
    let data = bench_dataset(&tmp);
    let stem = tmp.path("bench");
    let said = ok(&[
        "bench",
        "--dataset",
        data.to_str().unwrap(),
        "--images",
        "1",
        "--views",
        "1",
        "--reference-steps",
        "8",
        "--steps",
        "4",
        "--resolution",
        "16",
        "--samples",
        "4",
        "--out",
        stem.to_str().unwrap(),
    ]);
    for ext in ["json", "png", "md"] {
        assert!(stem.with_extension(ext).is_file(), "bench.{ext} missing");
    }
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(stem.with_extension("json")).unwrap()).unwrap();
    // The shipped defaults, found from the test's working folder (not the repository's) and
    // written relative to the repository: no machine's folder in the committed figures.
    assert_eq!(json["generator"], "models/chairs-campaign/generator.safetensors");
    assert_eq!(json["probe"], "models/chairs-probe/probe.safetensors");
    let points = json["points"].as_array().unwrap();
    let mut methods: Vec<&str> = points.iter().map(|p| p["method"].as_str().unwrap()).collect();
    methods.dedup();
    // Without --init: the reference, the defaults and ten speed options, each from the mean
    // code. At 16² and 4 + 4 samples `--grid auto` builds no grid (16 + 16 per refresh).
    assert_eq!(methods.len(), 12, "{methods:?}");
    assert_eq!(said.matches("done: ").count(), 12, "{said}");
    assert!(methods.contains(&"mean code, defaults, grid auto (none at this size)"), "{methods:?}");
    assert!(methods.iter().all(|m| m.starts_with("mean code")), "{methods:?}");
    let last = |m: &str| points.iter().rev().find(|p| p["method"] == m).unwrap()["steps"].as_u64();
    assert_eq!(last(methods[0]), Some(8), "the reference runs --reference-steps");
    assert_eq!(last(methods[1]), Some(4), "the others run --steps");
    // Before any step every method holds the same start and is scored the same way, so
    // their rows agree exactly.
    let starts: Vec<&serde_json::Value> = points.iter().filter(|p| p["steps"] == 0).collect();
    assert_eq!(starts.len(), 12);
    for p in &starts {
        for key in ["input_psnr", "input_ssim", "novel_psnr", "novel_ssim", "structure_agreement"] {
            assert_eq!(p[key], starts[0][key], "{key} of {} at 0 steps", p["method"]);
        }
    }
    let table = std::fs::read_to_string(stem.with_extension("md")).unwrap();
    assert!(table.contains("first point with ≥ 95 % of the gain"), "{table}");
    assert_eq!(points[0]["novel_psnr_per_object"].as_array().map(Vec::len), Some(1));

    // --only keeps the reference, the defaults and the methods named; --skip passes over
    // held-out objects, and asking past them names the flag; --noise-seeds inverts every
    // object once per seed and averages over all of them.
    let meta = gdrf_core::data::Metadata::load(&data).unwrap();
    let held = meta.images.iter().filter(|r| r.split == gdrf_core::data::Split::HeldOut).count();
    assert!(held >= 3, "the bench dataset holds {held} held-out images");
    let (skip, past) = ((held - 2).to_string(), (held - 1).to_string());
    let only = tmp.path("only");
    let mut args = vec!["bench", "--dataset", data.to_str().unwrap(), "--views", "1", "--reference-steps", "2"];
    args.extend(["--steps", "2", "--resolution", "16", "--samples", "4", "--only", "grid 32 cells,bf16"]);
    args.extend(["--noise-seeds", "3,5", "--images", "2", "--skip", &skip, "--out", only.to_str().unwrap()]);
    let said = ok(&args);
    assert_eq!(said.matches("done: ").count(), 4, "{said}");
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(only.with_extension("json")).unwrap()).unwrap();
    assert_eq!(json["skip"].as_u64(), Some(held as u64 - 2));
    assert_eq!(json["noise_seeds"], serde_json::json!([3, 5]));
    let floats =
        |v: &serde_json::Value| -> Vec<f64> { v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect() };
    for p in json["points"].as_array().unwrap() {
        let (objects, seeds) = (floats(&p["novel_psnr_per_object"]), floats(&p["novel_psnr_per_noise_seed"]));
        assert_eq!((objects.len(), seeds.len()), (2, 2), "{p}");
        // Both are means over the same four inversions, as is the point's own score.
        let mean = p["novel_psnr"].as_f64().unwrap();
        for m in [objects.iter().sum::<f64>() / 2.0, seeds.iter().sum::<f64>() / 2.0] {
            assert!((m - mean).abs() <= 1e-9 * mean.abs(), "{m} against {mean} in {p}");
        }
        // Before a step both seeds hold the same start; after two steps their noise has
        // moved them apart.
        if p["steps"] == 0 {
            assert_eq!(seeds[0], seeds[1], "{p}");
        } else if p["steps"] == 2 {
            assert_ne!(seeds[0], seeds[1], "{p}");
        }
    }
    let table = std::fs::read_to_string(only.with_extension("md")).unwrap();
    assert!(table.contains("noise seed(s) [3, 5]"), "{table}");
    let seeds_at = args.iter().position(|a| *a == "3,5").unwrap();
    args[seeds_at] = "3,3";
    fails(&args, &["--noise-seeds", "seed 3 is given twice"]);
    args[seeds_at] = "3,5";
    let last = args.len() - 1;
    args[last - 2] = past.as_str();
    fails(&args, &[&format!("held-out images after --skip {past}"), "--images asks for 2"]);
}
