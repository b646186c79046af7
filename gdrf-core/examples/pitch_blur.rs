//! How far image sharpness, rather than geometry, moves the evaluation probe's pitch: the
//! probe's mean signed pitch error (probe − truth, degrees) and mean absolute error on
//!   - the dataset's held-out images at 64², and seen through lower resolutions;
//!   - a generator's images as the evaluation renders them (one ray per pixel centre), the
//!     same rendered at 2× and antialiased down (as the dataset is supersampled), and the
//!     plain renders sharpened (unsharp mask).
//!
//! Each row has a sharpness figure beside it (mean squared Laplacian of the grey image),
//! so that generated images can be placed on the real images' blur-to-bias line.
//!
//! `tone` instead asks the same of the chairs' tone: each row gives the mean darkness
//! (1 − grey, in [0, 1]) of the chair's pixels (darker than 0.03), its spread and the share
//! of the image darker than 0.03, 0.1 and 0.3. The real images are also scored with the
//! chair's darkness scaled to the generated chairs' mean, the generated ones to the real
//! chairs' (the background stays white), and both with their faint pixels (darkness below
//! 0.1 or 0.3) made white.
//!
//! `cargo run --release -p gdrf-core --example pitch_blur -- GENERATOR DATASET PROBE [N] [SAMPLES] [quick|tone]`
//! (`quick`: the generator's plain and sharpened renders only).
use gdrf_core::camera::Poses;
use gdrf_core::checkpoint::load_generator;
use gdrf_core::data::Split;
use gdrf_core::eval::evaluator::render_codes;
use gdrf_core::eval::metrics::through_resolution;
use gdrf_core::eval::probe::{load_labelled, Probe};
use gdrf_core::pretrained::effnet::EfficientNetLite0;
use gdrf_core::rng::{Purpose, RandomSource, StepRng};
use gdrf_core::RenderConfig;
use std::path::Path;
use tch::{Device, Kind, Tensor};

/// Mean squared Laplacian of the grey image, `(N, 3, S, S)` in [−1, 1].
fn sharpness(x: &Tensor) -> f64 {
    let grey = x.to_kind(Kind::Float).mean_dim(1, true, Kind::Float);
    let k = Tensor::from_slice(&[0f32, 1., 0., 1., -4., 1., 0., 1., 0.]).view([1, 1, 3, 3]);
    let lap = grey.conv2d(&k, None::<Tensor>, 1, 0, 1, 1);
    f64::try_from(lap.square().mean(Kind::Double)).unwrap()
}

/// The chair's pixels of `(N, 3, S, S)` in [−1, 1] on a white background: (mean darkness
/// 1 − grey in [0, 1], its standard deviation, the share of pixels darker than 0.03, 0.1
/// and 0.3), over the batch.
fn tone(x: &Tensor) -> (f64, f64, [f64; 3]) {
    let grey = (x.to_kind(Kind::Float).mean_dim(1, false, Kind::Float) + 1.0) / 2.0;
    let dark: Tensor = (grey.neg() + 1.0).clamp(0.0, 1.0);
    let mask = dark.gt(0.03).to_kind(Kind::Float);
    let n = f64::try_from(mask.sum(Kind::Double)).unwrap();
    let mean = f64::try_from((&dark * &mask).sum(Kind::Double)).unwrap() / n;
    let var = f64::try_from(((&dark - mean).square() * &mask).sum(Kind::Double)).unwrap() / n;
    let share = |t: f64| f64::try_from(dark.gt(t).to_kind(Kind::Float).mean(Kind::Double)).unwrap();
    (mean, var.sqrt(), [share(0.03), share(0.1), share(0.3)])
}

/// `x` with every pixel's darkness (1 − value, per channel, in [0, 1]) scaled by `k`: white
/// stays white, the chair darkens (k > 1) or lightens.
fn darken(x: &Tensor, k: f64) -> Tensor {
    let darkness: Tensor = (x.neg() + 1.0) * k;
    (darkness.neg() + 1.0).clamp(-1.0, 1.0)
}

/// `x` with every pixel whose darkness (1 − grey, in [0, 1]) is below `t` made white: a
/// faint haze around the chair removed.
fn dehaze(x: &Tensor, t: f64) -> Tensor {
    let grey = (x.mean_dim(1, true, Kind::Float) + 1.0) / 2.0;
    let faint = grey.gt(1.0 - t).expand_as(x);
    x.where_self(&faint.logical_not(), &x.ones_like())
}

/// (signed, absolute) mean pitch error in degrees.
fn pitch_errors(probe: &Probe, effnet: &EfficientNetLite0, x: &Tensor, truth: &Tensor) -> anyhow::Result<(f64, f64)> {
    let mut preds = Vec::new();
    for chunk in x.split(64, 0) {
        preds.push(tch::no_grad(|| probe.predict(Some(effnet), &chunk))?.poses.select(1, 0));
    }
    let d =
        (Tensor::cat(&preds, 0).to_kind(Kind::Double) - truth.to_kind(Kind::Double)) * (180.0 / std::f64::consts::PI);
    Ok((f64::try_from(d.mean(Kind::Double))?, f64::try_from(d.abs().mean(Kind::Double))?))
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    anyhow::ensure!(args.len() >= 4, "usage: pitch_blur GENERATOR DATASET PROBE [N] [SAMPLES]");
    let num: i64 = args.get(4).map(|s| s.parse()).transpose()?.unwrap_or(256);
    let samples: usize = args.get(5).map(|s| s.parse()).transpose()?.unwrap_or(12);
    let quick = args.get(6).is_some_and(|s| s == "quick");
    let toned = args.get(6).is_some_and(|s| s == "tone");
    tch::set_num_threads(1);
    let device = Device::Cpu;
    let probe = Probe::load(Path::new(&args[3]), device)?;
    let effnet = EfficientNetLite0::load(&EfficientNetLite0::default_path(), device)?;
    let row = |what: &str, x: &Tensor, truth: &Tensor| -> anyhow::Result<()> {
        let (bias, abs) = pitch_errors(&probe, &effnet, x, truth)?;
        println!("| {what} | {:.3} | {bias:+.2}° | {abs:.2}° |", sharpness(x));
        Ok(())
    };
    let tone_row = |what: &str, x: &Tensor, truth: &Tensor| -> anyhow::Result<()> {
        let (bias, abs) = pitch_errors(&probe, &effnet, x, truth)?;
        let (dark, spread, cover) = tone(x);
        let [c0, c1, c2] = cover;
        println!("| {what} | {dark:.3} | {spread:.3} | {c0:.3}, {c1:.3}, {c2:.3} | {bias:+.2}° | {abs:.2}° |");
        Ok(())
    };
    if toned {
        println!("| images | chair darkness | its spread | share darker than 0.03, 0.1, 0.3 | signed pitch error | mean pitch error |");
        println!("|---|---|---|---|---|---|");
    } else {
        println!("| images | sharpness | signed pitch error | mean pitch error |\n|---|---|---|---|");
    }

    let data = load_labelled(Path::new(&args[2]), 64, 1, &|_| {})?;
    let (held, truth, _) = data.split(Split::HeldOut, None);
    let real_pitch = truth.poses.select(1, 0);
    if !toned {
        row(&format!("real, 64² ({})", held.size()[0]), &held, &real_pitch)?;
    }
    for low in if quick || toned { vec![] } else { vec![48, 40, 32, 24, 16] } {
        row(&format!("real through {low}²"), &through_resolution(&held, low), &real_pitch)?;
    }

    let loaded = load_generator(Path::new(&args[1]), device, Kind::Float)?;
    let g = &loaded.generator;
    let cam = loaded.header.camera.clone().ok_or_else(|| anyhow::anyhow!("the generator records no camera"))?;
    // Codes and poses from a seed the evaluation does not use (its seeds are 0–5).
    let z = StepRng::new(100, 0, Purpose::EvalCodes, Kind::Float, device).normal(&[num, g.cfg.latent_dim as i64]);
    let poses = Poses::sample_from(&cam, num, &mut StepRng::new(100, 0, Purpose::EvalPoses, Kind::Float, device));
    let rc = RenderConfig { num_steps: samples, jitter: false, ..RenderConfig::default() };
    let render = |res: i64| -> anyhow::Result<Tensor> {
        Ok(render_codes((g, None), &cam, &rc, (&z, &z), &poses, res, &mut |_| {})?)
    };
    let gen_pitch = poses.pitch.shallow_clone();
    let plain = render(64)?;
    if toned {
        let (real_dark, generated_dark) = (tone(&held).0, tone(&plain).0);
        tone_row(&format!("real, 64² ({})", held.size()[0]), &held, &real_pitch)?;
        tone_row(&format!("generated, 64² ({num}, {samples} + {samples} samples)"), &plain, &gen_pitch)?;
        let k = generated_dark / real_dark;
        tone_row(&format!("real, chair darkness × {k:.3}"), &darken(&held, k), &real_pitch)?;
        tone_row(&format!("generated, chair darkness × {:.3}", 1.0 / k), &darken(&plain, 1.0 / k), &gen_pitch)?;
        for t in [0.1, 0.3] {
            tone_row(&format!("real, darkness below {t} made white"), &dehaze(&held, t), &real_pitch)?;
            tone_row(&format!("generated, darkness below {t} made white"), &dehaze(&plain, t), &gen_pitch)?;
        }
        return Ok(());
    }
    row(&format!("generated, 64² ({num}, {samples} + {samples} samples)"), &plain, &gen_pitch)?;
    for low in if quick { vec![] } else { vec![48, 32] } {
        row(&format!("generated through {low}²"), &through_resolution(&plain, low), &gen_pitch)?;
    }
    // Unsharp mask: x + a·(x − blur(x)), blur = through 32².
    let blurred = through_resolution(&plain, 32);
    for a in [0.5, 1.0] {
        let sharp = (&plain + (&plain - &blurred) * a).clamp(-1.0, 1.0);
        row(&format!("generated, sharpened {a}"), &sharp, &gen_pitch)?;
    }
    if !quick {
        let double = gdrf_core::io::resize(&render(128)?, 64);
        row("generated at 128², antialiased to 64²", &double, &gen_pitch)?;
    }
    Ok(())
}
