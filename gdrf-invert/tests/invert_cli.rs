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

/// Runs gdrf-invert, which must succeed, and returns what it wrote to standard error (the
/// lines that say what it does, before the optimisation).
fn said_first(args: &[&str]) -> String {
    let o = gdrf_invert(args);
    assert!(o.status.success(), "gdrf-invert {args:?} failed:\n{}", text(&o));
    String::from_utf8_lossy(&o.stderr).into_owned()
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
    gdrf_core::data::synth::generate(&data, &opts, 2, &|_| {}).unwrap();
    data
}

/// The procedural chair of [`photo_in`], opaque on a 96 × 80 grey canvas at (6, 40): small
/// and off-centre, as no training image has it, with no alpha channel.
fn grey_photo_in(dir: &TempDir) -> String {
    let chair = image::open(photo_in(dir)).unwrap().to_rgb8();
    let mut canvas = image::RgbImage::from_pixel(96, 80, image::Rgb([120, 120, 130]));
    for (x, y, p) in chair.enumerate_pixels() {
        // The chair's white background becomes the canvas's grey.
        if p.0.iter().any(|&c| c < 250) {
            canvas.put_pixel(6 + x, 40 + y, *p);
        }
    }
    let path = dir.path("grey.png");
    canvas.save(&path).unwrap();
    path.display().to_string()
}

#[test]
fn a_photo_is_framed_and_its_silhouette_is_matched() {
    let tmp = TempDir::new("invert-frame").unwrap();
    let photo = grey_photo_in(&tmp);
    let run = |name: &str, extra: &[&str]| -> (String, serde_json::Value) {
        let out = tmp.path(name);
        let mut args = vec![photo.as_str(), "--steps", "2", "--resolution", "16", "--samples", "4", "--orbit", "0"];
        args.extend(["--quiet", "--out", out.to_str().unwrap()]);
        args.extend(extra);
        let said = said_first(&args);
        let report = serde_json::from_str(&std::fs::read_to_string(out.join("invert.json")).unwrap()).unwrap();
        (said, report)
    };
    // As written: the grey background is found on the border and becomes white, the chair is
    // framed as the shipped model's training images frame theirs (framing.json beside it),
    // and its silhouette is matched; the first line says so.
    let weight = format!("silhouette term weight {}", gdrf_core::invert::InvertConfig::SILHOUETTE_WEIGHT);
    let (said, r) = run("auto", &[]);
    let first = said.lines().next().unwrap();
    assert!(first.starts_with("photo 96×80: silhouette from the uniform background (RGB 120, 120, 130)"), "{said}");
    assert!(first.contains("framed as in the training images"), "{said}");
    assert!(said.contains(&weight), "{said}");
    let fr = &r["framing"];
    assert_eq!((fr["reframed"].as_bool(), fr["silhouette_from"]["background"].is_array()), (Some(true), true), "{r}");
    assert!(fr["framing_file"].as_str().unwrap().ends_with("models/chairs-campaign/framing.json"), "{r}");
    let history = r["history"].as_array().unwrap();
    assert!(history.iter().all(|l| l["silhouette"].as_f64().unwrap() > 0.0), "{r}");
    // The framed photo has a white background and the chair inside its borders.
    let input = image::open(tmp.path("auto").join("input.png")).unwrap().to_rgb8();
    assert_eq!(input.get_pixel(0, 0).0, [255, 255, 255]);
    // The window holds the whole object: its box lies inside it.
    let (b, w) = (&fr["object_box"], &fr["window"]);
    let (x, y, side) = (w["x"].as_f64().unwrap(), w["y"].as_f64().unwrap(), w["side"].as_f64().unwrap());
    let b: Vec<f64> = b.as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    assert!(b[0] >= x && b[1] >= y && b[2] <= x + side && b[3] <= y + side, "{r}");

    // --fit crop keeps the centred square (the silhouette still found and matched) and
    // --silhouette-weight 0 turns the term off.
    let (said, r) = run("crop", &["--fit", "crop", "--silhouette-weight", "0"]);
    assert!(said.contains("silhouette term off"), "{said}");
    assert_eq!(r["framing"]["window"], serde_json::json!({"x": 8, "y": 0, "side": 80}), "{r}");
    assert_eq!(r["framing"]["reframed"], false);
    assert!(r["history"].as_array().unwrap().iter().all(|l| l["silhouette"] == 0.0), "{r}");

    // A border of many colours: no silhouette, a warning that names --mask; a mask finds it.
    let noisy = tmp.path("noisy.png");
    let mut img = image::open(&photo).unwrap().to_rgb8();
    for (x, y, p) in img.enumerate_pixels_mut() {
        if (x + y) % 2 == 0 {
            *p = image::Rgb([20, 200, 60]);
        }
    }
    img.save(&noisy).unwrap();
    let noisy_s = noisy.to_str().unwrap();
    let out = tmp.path("noisy-out");
    let said = said_first(&[
        noisy_s,
        "--steps",
        "1",
        "--resolution",
        "16",
        "--samples",
        "4",
        "--orbit",
        "0",
        "--quiet",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(said.contains("no silhouette") && said.contains("warning:") && said.contains("--mask"), "{said}");
    assert!(said.contains("no silhouette term"), "{said}");
    let mut mask = image::GrayImage::new(96, 80);
    for y in 40..72 {
        for x in 6..38 {
            mask.put_pixel(x, y, image::Luma([255]));
        }
    }
    mask.save(tmp.path("mask.png")).unwrap();
    let out = tmp.path("masked");
    let m = tmp.path("mask.png");
    let said = said_first(&[
        noisy_s,
        "--mask",
        m.to_str().unwrap(),
        "--steps",
        "1",
        "--resolution",
        "16",
        "--samples",
        "4",
        "--orbit",
        "0",
        "--quiet",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(said.starts_with("photo 96×80: silhouette from --mask"), "{said}");
    assert!(said.contains(&weight), "{said}");
}

#[test]
fn framing_measures_the_training_split_beside_the_generator() {
    let tmp = TempDir::new("invert-framing").unwrap();
    let data = bench_dataset(&tmp);
    let gen = tmp.path("model/generator.safetensors");
    std::fs::create_dir_all(gen.parent().unwrap()).unwrap();
    std::fs::copy(gdrf_core::paths::shipped_generator(), &gen).unwrap();
    let g = gen.to_str().unwrap();
    let said = ok(&["framing", "--dataset", data.to_str().unwrap(), "--generator", g, "--quiet"]);
    let meta = gdrf_core::data::Metadata::load(&data).unwrap();
    let train = meta.images.iter().filter(|r| r.split == gdrf_core::data::Split::Train).count();
    assert!(said.starts_with(&format!("{train} images:")), "{said}");
    let f = gdrf_core::invert::framing::Framing::beside(&gen).unwrap().expect("framing.json beside the generator");
    assert_eq!(f.images, train);
    assert!(0.0 < f.size[0] && f.size[0] <= f.size[1] && f.size[1] <= 1.0, "{f:?}");
    // A folder of opaque images has nothing to measure, and says so.
    let flat = tmp.path("flat");
    std::fs::create_dir_all(&flat).unwrap();
    image::RgbImage::from_pixel(8, 8, image::Rgb([9, 9, 9])).save(flat.join("a.png")).unwrap();
    fails(&["framing", "--dataset", flat.to_str().unwrap(), "--generator", g], &["have no alpha", "flat"]);
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
    // --pose and an initialiser the photo starts at that camera's mean pose (car: pitch
    // 1.2217 rad, yaw 0).
    let car = tmp.path("car");
    let mut args = vec![photo.as_str(), "--camera", "car", "--init", "none", "--out", car.to_str().unwrap()];
    args.extend(small);
    ok(&args);
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(car.join("invert.json")).unwrap()).unwrap();
    assert_eq!(report["camera"]["fov_deg"], 30.0);
    let start = &report["start_pose_deg"];
    assert!((start[0].as_f64().unwrap() - 1.2217f64.to_degrees()).abs() < 1e-9, "{start}");
    assert_eq!(start[1].as_f64(), Some(0.0), "{start}");

    // Without --resolution and --samples it inverts where the generator learned (the shipped
    // header: 64², 24 samples per ray, so 12 + 12); a generator without that record gets 64²
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
    assert_eq!((res, n), (64, 12));
    assert!(said.contains("at 64² (where the generator learned) with 12 + 12 samples"), "{said}");
    let (res, n, said) = config_of(&["--generator", bare.to_str().unwrap()], "bare");
    assert_eq!((res, n), (64, 24));
    assert!(!said.contains("where the generator learned"), "{said}");
    let (res, n, _) = config_of(&["--resolution", "16", "--samples", "4"], "given");
    assert_eq!((res, n), (16, 4));

    // --grid takes gdrf-edit's values. `auto` counts the samples one grid serves: 10 steps
    // (--grid-refresh) × 64² pixels × 24 samples = 983 040, over 100 000 (and under a
    // million), so a 32³ grid sampled only in its cells; refreshed every step, 98 304, so
    // none. Off by default.
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
    assert_eq!(grid_of(&["--grid", "auto", "--grid-refresh", "1"], "grid-auto-1"), (0, false));
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

/// The JSON file at `path`.
fn json_at(path: &std::path::Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))).unwrap()
}

#[test]
fn the_initialiser_trains_ships_starts_inversions_by_default_and_is_refused_by_another_generator() {
    let tmp = TempDir::new("invert-cli-init").unwrap();
    let photo = photo_in(&tmp);
    let data = bench_dataset(&tmp);
    let init = tmp.path("init.safetensors");
    let i = init.to_str().unwrap();
    // The shipped generator in a folder of its own, and its initialiser shipped beside it.
    let model = tmp.path("model");
    std::fs::create_dir_all(&model).unwrap();
    let generator = model.join("generator.safetensors");
    std::fs::copy(gdrf_core::paths::shipped_generator(), &generator).unwrap();
    let gen = generator.to_str().unwrap();
    let shipped = model.join("initialiser.safetensors");
    // A small initialiser run: 24 tuples (8 held out) at 16², and the small dataset's
    // training-split images at their poses (2 held out), validation every 2 steps.
    let small = |steps: &'static str, extra: &[&str]| -> Vec<String> {
        let mut v = vec!["train-init", "--generator", gen, "--out", i, "--count", "24", "--held-out", "8"];
        v.extend(["--steps", steps, "--eval-interval", "2", "--resolution", "16", "--samples", "4"]);
        v.extend(["--batch-size", "8", "--real", data.to_str().unwrap(), "--real-batch", "2", "--real-held-out", "2"]);
        v.extend(["--quiet"]);
        v.extend(extra);
        v.into_iter().map(String::from).collect()
    };
    let said = ok(&as_args(&small("4", &["--ship", shipped.to_str().unwrap()])));
    // Each validation is reported as it happens, also when the output is not a terminal:
    // 8 rendered and 2 real images a step.
    for (step, images) in [(2, 20), (4, 40)] {
        assert!(said.contains(&format!("step {step} ({images} images): held-out w_s MSE")), "{said}");
    }
    assert!(said.contains("real images: pitch"), "{said}");
    let report = json_at(&tmp.path("init.safetensors.json"));
    assert_eq!(report["evaluations"].as_array().unwrap().len(), 2);
    assert!(tmp.path("init.safetensors.png").is_file(), "the curve");
    assert!(shipped.is_file(), "--ship");
    // Not overwritten without --resume; --resume continues to a longer run, and the curve
    // keeps the evaluations before it.
    fails(&["train-init", "--generator", gen, "--out", i, "--steps", "6"], &["--resume"]);
    ok(&as_args(&small("6", &["--resume"])));
    assert_eq!(json_at(&tmp.path("init.safetensors.json"))["evaluations"].as_array().unwrap().len(), 3);
    // --head-only needs a start to keep; with --warm-from it starts from the shipped file,
    // trains the head alone and says so, in its log and its report.
    let warm = tmp.path("warm.safetensors");
    let w = warm.to_str().unwrap();
    fails(&["train-init", "--generator", gen, "--out", w, "--head-only"], &["--head-only", "--warm-from"]);
    assert!(!warm.exists(), "nothing written for a refused flag");
    let mut args = small("2", &["--warm-from", shipped.to_str().unwrap(), "--head-only"]);
    args[4] = w.to_string(); // --out
    let said = ok(&as_args(&args));
    assert!(said.contains("ResNet-34's head, its backbone kept"), "{said}");
    assert!(said.contains("starting from the weights of"), "{said}");
    let r = json_at(&tmp.path("warm.safetensors.json"));
    assert!(r["warm_from"].as_str().unwrap().ends_with("model/initialiser.safetensors"), "{r}");
    assert_eq!(r["config"]["head_only"], true);

    let m = load_generator(&generator, Device::Cpu, Kind::Float).unwrap();
    let id = generator_id(&m.vs, &m.generator);
    let invert = |name: &str, extra: &[&str]| -> (String, serde_json::Value) {
        let out = tmp.path(name);
        let mut args = vec![photo.as_str(), "--generator", gen, "--resolution", "16", "--samples", "4"];
        args.extend(["--orbit", "0", "--quiet", "--out", out.to_str().unwrap()]);
        args.extend(extra);
        let said = ok(&args);
        (said, json_at(&out.join("invert.json")))
    };
    // By default the initialiser beside the generator starts w_s and estimates the pose,
    // which is refined with the features; the output says so.
    let (said, r) = invert("default", &["--steps", "2"]);
    assert!(said.contains("w_s starts at the prediction of the initialiser"), "{said}");
    assert!(said.contains("(estimated by the initialiser)") && said.contains("refined with the features"), "{said}");
    assert_eq!((r["pose_from"].as_str(), r["refine_pose"].as_bool()), (Some("initialiser"), Some(true)), "{r}");
    assert!(r["init"].as_str().unwrap().ends_with("initialiser.safetensors"), "{r}");
    assert_eq!(r["start_pose_deg"], r["predicted_pose_deg"], "{r}");
    // --pose overrides the estimate, which is reported beside it, and is not refined.
    let (said, r) = invert("given", &["--steps", "2", "--pose", "62.5,-8.2"]);
    assert!(said.contains("pitch 62.5°, yaw -8.2° (given by --pose)"), "{said}");
    assert!(said.contains("the initialiser's estimate"), "{said}");
    assert_eq!((r["pose_from"].as_str(), r["refine_pose"].as_bool()), (Some("given"), Some(false)), "{r}");
    // (Degrees through radians and back: equal to the last few bits.)
    let used: Vec<f64> = r["pose_deg"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    assert!(used.len() == 2 && (used[0] - 62.5).abs() < 1e-9 && (used[1] + 8.2).abs() < 1e-9, "{used:?}");
    // --init none: the mean code's features, exactly, after 0 steps.
    let (said, r) = invert("none", &["--steps", "0", "--init", "none", "--pose", "62.5,-8.2"]);
    assert!(said.contains("--init none: w_s starts at the mean code's"), "{said}");
    assert_eq!(r["init"], serde_json::Value::Null);
    let f = Features::load(&tmp.path("none").join("features.safetensors"), &m.generator, &id).unwrap();
    let mean =
        gdrf_core::invert::Start::mean(&m.generator, (0.0, 0.0), gdrf_core::field::generator::TRUNCATION_MEAN_CODES);
    // (Equal up to the reduction order of the mean over 10 000 codes in two processes.)
    let a = gdrf_core::nn::film::Film::from_raw(&mean.appearance_raw);
    assert!(f.w_s.allclose(&mean.w_s, 1e-6, 1e-7, false), "w_s is not the mean code's");
    assert!(
        f.appearance.gamma.allclose(&a.gamma, 1e-6, 1e-6, false)
            && f.appearance.beta.allclose(&a.beta, 1e-6, 1e-7, false)
    );

    // Another generator (one weight changed) beside this initialiser refuses it, naming both
    // identities, whether it was found beside it or given; --init none still inverts.
    let other_dir = tmp.path("other");
    std::fs::create_dir_all(&other_dir).unwrap();
    let mut o = load_generator(&generator, Device::Cpu, Kind::Float).unwrap();
    tch::no_grad(|| {
        let mut w = o.vs.variables()["deform.head.bias"].shallow_clone();
        let _ = w.g_add_scalar_(0.01);
    });
    let other = other_dir.join("generator.safetensors");
    save_generator(&other, &o.vs, &o.header).unwrap();
    let other_id = generator_id(&o.vs, &o.generator);
    let _ = &mut o;
    std::fs::copy(&shipped, other_dir.join("initialiser.safetensors")).unwrap();
    let out = tmp.path("refused");
    let o = out.to_str().unwrap();
    let ot = other.to_str().unwrap();
    fails(&[&photo, "--generator", ot, "--out", o], &["trained for generator", &id, &other_id, "--init none"]);
    fails(&[&photo, "--generator", ot, "--init", i, "--out", o], &["--init", "trained for generator", &id, &other_id]);
    assert!(!out.exists(), "a refused run created its output folder");
    std::fs::remove_file(other_dir.join("initialiser.safetensors")).unwrap();
    // A generator without one says so and starts from the mean code.
    let said = ok(&[
        &photo,
        "--generator",
        ot,
        "--steps",
        "1",
        "--resolution",
        "16",
        "--samples",
        "4",
        "--orbit",
        "0",
        "--quiet",
        "--out",
        o,
    ]);
    assert!(said.contains("no initialiser beside") && said.contains("mean code"), "{said}");
    assert!(said.contains("the camera's mean pose"), "{said}");

    // The bench with this initialiser: the mean code and the initialiser at the true pose,
    // gdrf-invert's defaults and the paper's steps (on --reference-images objects), with the
    // variants on request; the initialiser named in the JSON.
    let stem = tmp.path("bench");
    let (d, s) = (data.to_str().unwrap(), stem.to_str().unwrap());
    let mut args = vec!["bench", "--generator", gen, "--dataset", d, "--samples", "4", "--out", s, "--skip", "0"];
    args.extend(["--images", "2", "--views", "2", "--reference-steps", "4", "--reference-images", "1", "--steps", "2"]);
    args.extend(["--resolution", "16", "--variants", "--figure-objects", "2"]);
    let said = ok(&args);
    assert_eq!(said.matches("done: ").count(), 6, "{said}");
    let json = json_at(&stem.with_extension("json"));
    assert!(json["init"].as_str().unwrap().ends_with("model/initialiser.safetensors"), "{}", json["init"]);
    let points = json["points"].as_array().unwrap();
    let by = |m: &str| -> Vec<&serde_json::Value> {
        points.iter().filter(|p| p["method"].as_str().unwrap().starts_with(m)).collect()
    };
    let paper = by("paper");
    assert_eq!((paper[0]["objects"].as_u64(), paper.last().unwrap()["steps"].as_u64()), (Some(1), Some(4)));
    assert_eq!(by("gdrf-invert").last().unwrap()["objects"].as_u64(), Some(2));
    // Gains are over the mean code at the true pose before any step: 0 there, exactly.
    assert_eq!(by("mean code")[0]["novel_gain_db"].as_f64(), Some(0.0));
    // The true pose has no pose error; the estimated one has, as a wrapped angle.
    assert!(by("initialiser, true")[0]["yaw_error_deg"].is_null());
    let yaw = by("gdrf-invert")[0]["yaw_error_deg"].as_f64().unwrap();
    assert!((0.0..=180.0).contains(&yaw), "{yaw}");
    for p in points {
        for key in ["silhouette_iou", "structure_agreement"] {
            let v = p[key].as_f64().unwrap();
            assert!((0.0..=1.0).contains(&v), "{key} {v} in {p}");
        }
        assert!(p["novel_perceptual"].as_f64().unwrap() >= 0.0, "{p}");
    }
    for f in [stem.with_extension("md"), stem.with_extension("png"), tmp.path("bench-figure.png")] {
        assert!(f.is_file(), "{} missing", f.display());
    }
    // Two objects' rows of 1 + 1 + 2 + 2 tiles, 16² each, drawn three times larger.
    let fig = image::open(tmp.path("bench-figure.png")).unwrap();
    assert_eq!((fig.width(), fig.height()), (6 * 16 * 3, 2 * 16 * 3));
    assert!(std::fs::read_to_string(stem.with_extension("md")).unwrap().contains("EfficientNet-Lite0"));

    // --restyle: the same objects photographed out of the house style, the photos written
    // beside the stem (the same bytes for the same seed), and a row that inverts them as
    // they are.
    let restyled = |name: &str| -> (String, std::path::PathBuf) {
        let stem = tmp.path(name);
        let mut args = vec!["bench", "--generator", gen, "--dataset", d, "--samples", "4", "--skip", "0"];
        args.extend(["--images", "2", "--views", "2", "--steps", "2", "--resolution", "16", "--only", "gdrf-invert"]);
        args.extend(["--restyle", "3", "--figure-objects", "0", "--out", stem.to_str().unwrap()]);
        (ok(&args), stem)
    };
    let (said, stem) = restyled("restyled");
    assert_eq!(said.matches("done: ").count(), 3, "{said}");
    assert!(said.contains("done: gdrf-invert, the photo as it is"), "{said}");
    let json = json_at(&stem.with_extension("json"));
    assert_eq!(json["restyle"], 3);
    let photos = |dir: &str| -> Vec<Vec<u8>> {
        let mut files: Vec<_> = std::fs::read_dir(tmp.path(dir)).unwrap().map(|e| e.unwrap().path()).collect();
        files.sort();
        files.iter().map(|f| std::fs::read(f).unwrap()).collect()
    };
    let first = photos("restyled-photos");
    assert_eq!(first.len(), 2);
    for bytes in &first {
        let img = image::load_from_memory_with_format(bytes, image::ImageFormat::Jpeg).unwrap();
        assert!(!img.color().has_alpha() && img.width().min(img.height()) >= 96, "{:?}", img.color());
    }
    restyled("again");
    assert_eq!(photos("again-photos"), first, "the same seed draws the same photos");
}

#[test]
fn the_bench_averages_objects_and_noise_seeds_and_names_bad_flags() {
    let tmp = TempDir::new("invert-bench").unwrap();
    let data = bench_dataset(&tmp);
    let meta = gdrf_core::data::Metadata::load(&data).unwrap();
    let held = meta.images.iter().filter(|r| r.split == gdrf_core::data::Split::HeldOut).count();
    assert!(held >= 3, "the bench dataset holds {held} held-out images");
    let (skip, past) = ((held - 2).to_string(), (held - 1).to_string());
    let stem = tmp.path("bench");
    // With --init none only the mean code runs, from the test's working folder: the shipped
    // generator and probe are found, and written relative to the repository.
    let mut args = vec!["bench", "--init", "none", "--dataset", data.to_str().unwrap(), "--views", "1"];
    args.extend(["--steps", "2", "--resolution", "16", "--samples", "4", "--figure-objects", "0"]);
    args.extend(["--noise-seeds", "3,5", "--images", "2", "--skip", &skip, "--out", stem.to_str().unwrap()]);
    let said = ok(&args);
    assert_eq!(said.matches("done: ").count(), 1, "{said}");
    let json = json_at(&stem.with_extension("json"));
    assert_eq!(json["generator"], "models/chairs-campaign/generator.safetensors");
    assert_eq!(json["probe"], "models/chairs-probe/probe.safetensors");
    assert_eq!(json["init"], serde_json::Value::Null);
    assert_eq!(json["skip"].as_u64(), Some(held as u64 - 2));
    assert_eq!(json["noise_seeds"], serde_json::json!([3, 5]));
    assert!(!tmp.path("bench-figure.png").exists(), "--figure-objects 0 draws none");
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
    let table = std::fs::read_to_string(stem.with_extension("md")).unwrap();
    assert!(table.contains("noise seeds [3, 5]"), "{table}");
    let seeds_at = args.iter().position(|a| *a == "3,5").unwrap();
    args[seeds_at] = "3,3";
    fails(&args, &["--noise-seeds", "seed 3 is given twice"]);
    args[seeds_at] = "3,5";
    let skip_at = args.iter().position(|a| *a == skip.as_str()).unwrap();
    args[skip_at] = past.as_str();
    fails(&args, &[&format!("held-out images after --skip {past}"), "--images asks for 2"]);
}
