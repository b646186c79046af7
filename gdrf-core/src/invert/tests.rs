use super::*;
use crate::nn::film::Film;
use crate::GeneratorConfig;
use tch::{nn, Device};

fn small() -> (nn::VarStore, Generator) {
    tch::manual_seed(3);
    let vs = nn::VarStore::new(Device::Cpu);
    let cfg = GeneratorConfig::tiny();
    let g = Generator::new(&vs.root(), &cfg).unwrap();
    // A fresh deformation head is zero (the release's start), so the shape would not
    // depend on w_s at all; a trained generator's does.
    tch::no_grad(|| {
        let mut w = vs.variables()["deform.head.weight"].shallow_clone();
        w.copy_(&(Tensor::randn(w.size(), (Kind::Float, Device::Cpu)) * 0.5));
    });
    (vs, g)
}

fn cfg(steps: usize) -> InvertConfig {
    InvertConfig {
        steps,
        resolution: 16,
        samples: 8,
        perceptual_weight: 0.0,
        lr: 0.02,
        ray_fraction: 1.0,
        ..Default::default()
    }
}

/// The target: seed 5's features rendered at `pose` (same noise convention as step 0).
fn target(g: &Generator, cam: &CameraConfig, pose: (f64, f64), res: i64) -> (Features, Tensor) {
    let f = Features::from_seed(g, 5);
    let rc = RenderConfig { num_steps: 8, jitter: false, ..Default::default() };
    let r = Renderer::new(g, cam, &rc).unwrap();
    let lat = Latents {
        shape: g.shape_from_w(&f.w_s, None),
        appearance: Film { gamma: f.appearance.gamma.shallow_clone(), beta: f.appearance.beta.shallow_clone() },
    };
    let n = Noise { jitter: None, importance: Some(Tensor::full([1, res * res, 8], 0.5, (Kind::Float, Device::Cpu))) };
    let img = tch::no_grad(|| render_at_pose(&r, &lat, pose, res, &n, None)).unwrap();
    (f, img)
}

#[test]
fn a_ray_subset_sees_the_whole_image_and_the_same_loss() {
    let (_vs, g) = small();
    let cam = CameraConfig::default();
    let (_, photo) = target(&g, &cam, (1.0, 0.0), 16);
    let start = Start::mean(&g, (1.0, 0.0), 100);
    let all = invert(&g, &cam, &photo, &start, &cfg(1), None, &mut |_| {}).unwrap();
    let part =
        invert(&g, &cam, &photo, &start, &InvertConfig { ray_fraction: 0.25, ..cfg(1) }, None, &mut |_| {}).unwrap();
    // Same noise, same image: the loss of step 0 agrees; only the update differs.
    let (a, b) = (all.history[0].loss, part.history[0].loss);
    assert!((a - b).abs() <= 1e-6 + 1e-5 * a.abs(), "{a} vs {b}");
    assert!(f64::try_from((&all.features.w_s - &part.features.w_s).abs().max()).unwrap() > 0.0);
}

#[test]
fn coarse_steps_patience_and_bad_settings() {
    let c = InvertConfig { steps: 10, coarse_fraction: 0.3, resolution: 32, ..Default::default() };
    assert_eq!((0..10).map(|s| c.resolution_at(s)).collect::<Vec<_>>(), [16, 16, 16, 32, 32, 32, 32, 32, 32, 32]);
    let (_vs, g) = small();
    let cam = CameraConfig::default();
    let (_, photo) = target(&g, &cam, (1.0, 0.0), 16);
    let start = Start::mean(&g, (1.0, 0.0), 100);
    // An improvement threshold no step can meet stops after `patience` steps past the first.
    let c = InvertConfig { patience: 3, min_improvement: 0.99, ..cfg(50) };
    let inv = invert(&g, &cam, &photo, &start, &c, None, &mut |_| {}).unwrap();
    assert!(inv.stopped_early);
    assert_eq!(inv.history.len(), 4);
    for (bad, key) in [
        (InvertConfig { lr: 0.0, ..cfg(1) }, "invert.lr"),
        (InvertConfig { ray_fraction: 0.0, ..cfg(1) }, "invert.ray_fraction"),
        (InvertConfig { coarse_fraction: 1.0, ..cfg(1) }, "invert.coarse_fraction"),
        (InvertConfig { prior_shape: -1.0, ..cfg(1) }, "invert.prior_shape"),
        (InvertConfig { samples: 2, ..cfg(1) }, "invert.samples"),
        (InvertConfig { grid: 2, ..cfg(1) }, "invert.grid"),
        (InvertConfig { grid_refresh: 0, ..cfg(1) }, "invert.grid_refresh"),
        (InvertConfig { grid_threshold: f64::NAN, ..cfg(1) }, "invert.grid_threshold"),
    ] {
        let e = invert(&g, &cam, &photo, &start, &bad, None, &mut |_| {}).unwrap_err().to_string();
        assert!(e.contains(key), "{e}");
    }
    let e = invert(&g, &cam, &photo.narrow(1, 0, 2), &start, &cfg(1), None, &mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("(1, 3, R, R)"), "{e}");
    let wrong = Start { w_s: Tensor::zeros([1, 3], (Kind::Float, Device::Cpu)), ..Start::mean(&g, (1.0, 0.0), 10) };
    assert!(invert(&g, &cam, &photo, &wrong, &cfg(1), None, &mut |_| {}).is_err());
}

#[test]
fn poses_parse_in_degrees_and_bad_ones_are_named() {
    let (p, y) = parse_pose_degrees(" 90, -45 ", "--pose").unwrap();
    assert_eq!((p, y), (std::f64::consts::FRAC_PI_2, -std::f64::consts::FRAC_PI_4));
    for bad in ["60", "60,x", "1,2,3", "nan,0", ""] {
        let e = parse_pose_degrees(bad, "--photo-pose").unwrap_err().to_string();
        assert!(e.contains("--photo-pose") && e.contains("PITCH,YAW"), "{bad}: {e}");
    }
}
