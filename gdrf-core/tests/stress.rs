//! Numerical stress suite: extreme densities, degenerate rays and weights, the exact
//! initial state of the regularisers, saturated discriminators, wrap-around poses, camera
//! poles, extreme fields of view and SIREN inputs, sampling only occupied bins, float32
//! against float64, and finite-difference gradient checks of every regulariser.
mod common;

use gdrf_core::camera::{cam2world_rotation, pixel_directions, Poses, Rays};
use gdrf_core::disc::Discriminator;
use gdrf_core::field::generator::Generator;
use gdrf_core::loss::deform_reg::{density_gradient, normal_distance, regularisers, RegConfig, RegSamples, RegVariant};
use gdrf_core::loss::{gan, LossConfig, Schedule};
use gdrf_core::nn::film::FilmLayer;
use gdrf_core::nn::siren::SineLayer;
use gdrf_core::nn::WeightInit;
use gdrf_core::render::sampler::{importance_depths, sample_pdf, OccupiedLength};
use gdrf_core::render::{composite, CompositeOptions, Noise, Renderer};
use gdrf_core::train::{discriminator_pass, generator_pass, FakeBatch};
use gdrf_core::{CameraConfig, GeneratorConfig, Latents, RenderConfig};
use std::f64::consts::PI;
use tch::{nn, Device, Kind, Tensor};

const CPU: Device = Device::Cpu;

fn finite(t: &Tensor) -> bool {
    bool::try_from(t.isfinite().all()).unwrap()
}
fn max(t: &Tensor) -> f64 {
    f64::try_from(t.max()).unwrap()
}
fn min(t: &Tensor) -> f64 {
    f64::try_from(t.min()).unwrap()
}

/// Builds a small generator in `kind`.
fn small_generator(kind: Kind, seed: i64) -> (nn::VarStore, Generator) {
    let mut vs = nn::VarStore::new(CPU);
    let cfg = GeneratorConfig { hidden_dim: 32, ..GeneratorConfig::tiny() };
    let g = gdrf_core::rng::with_global_seed(seed, || Generator::new(&vs.root(), &cfg).unwrap());
    if kind == Kind::Double {
        vs.double();
    }
    (vs, g)
}

fn all_grads_finite(vs: &nn::VarStore) -> bool {
    vs.variables().values().all(|v| {
        let g = v.grad();
        !g.defined() || finite(&g)
    })
}

#[test]
fn integrator_survives_extreme_densities() {
    let opts = (Kind::Float, CPU);
    let s = 24;
    // Rays: [0] densities over ±1e4, [1] +inf/−inf mixed, [2] all empty, [3] opaque first
    // sample, [4] zero-length intervals with infinite density, [5] huge values everywhere.
    let sigma = Tensor::linspace(-1e4, 1e4, s, opts).view([1, s, 1]).repeat([6, 1, 1]);
    let _ = sigma.get(1).narrow(0, 0, 12).fill_(f64::INFINITY);
    let _ = sigma.get(1).narrow(0, 12, 12).fill_(f64::NEG_INFINITY);
    let _ = sigma.get(2).fill_(-1e4);
    let _ = sigma.get(3).fill_(-50.0);
    let _ = sigma.get(3).get(0).fill_(1e4);
    let _ = sigma.get(4).fill_(f64::INFINITY);
    let _ = sigma.get(5).fill_(3e38);
    let z = Tensor::linspace(0.6, 1.4, s, opts).view([1, s, 1]).repeat([6, 1, 1]);
    let _ = z.get(4).fill_(1.0); // every interval has length 0
    let sigma = sigma.set_requires_grad(true);
    let rgb = Tensor::rand([6, s, 3], opts).set_requires_grad(true);
    for o in [
        CompositeOptions::default(),
        CompositeOptions { last_back: true, white_back: false, ..Default::default() },
        CompositeOptions { force_last_white: true, white_back: false, ..Default::default() },
    ] {
        let c = composite(&rgb, &sigma, &z, &o);
        for t in [&c.pixel, &c.depth, &c.weights, &c.opacity] {
            assert!(finite(t), "non-finite output with {o:?}: {t:?}");
        }
        let eps = o.widen_eps;
        assert!(min(&c.pixel) >= -eps - 1e-6 && max(&c.pixel) <= 1.0 + eps + 1e-6, "{o:?}");
        assert!(max(&c.weights.sum_dim_intlist(1, false, Kind::Float)) <= 1.0 + 1e-6);
        assert!(min(&c.weights) >= 0.0);
        assert!(min(&c.depth) >= 0.6 - 1e-6 && max(&c.depth) <= 1.4 + 1e-6, "depth {:?}", c.depth);
        assert!((c.depth.double_value(&[2, 0]) - 1.4).abs() < 1e-6, "empty ray depth is the far end");
        assert!((c.depth.double_value(&[3, 0]) - 0.6).abs() < 1e-6, "opaque first sample");
        let (gs, gc) = {
            let g = Tensor::run_backward(
                &[(c.pixel.sum(Kind::Float) + c.depth.sum(Kind::Float))],
                &[&sigma, &rgb],
                false,
                false,
            );
            (g[0].shallow_clone(), g[1].shallow_clone())
        };
        assert!(finite(&gs) && finite(&gc), "non-finite gradients with {o:?}");
    }
}

#[test]
fn importance_sampling_with_degenerate_weights() {
    let opts = (Kind::Float, CPU);
    let n = 16;
    let z = Tensor::linspace(0.6, 1.4, n, opts).view([1, n]).repeat([4, 1]);
    let w = Tensor::zeros([4, n], opts);
    let _ = w.get(1).get(8).fill_(1.0);
    let _ = w.get(2).get(1).fill_(1.0); // mass on a dropped end weight
    let _ = w.get(3).fill_(1e30);
    // Sorted uniforms including the ends of [0, 1).
    let u = Tensor::linspace(0.0, 1.0 - 1e-7, 64, opts).view([1, 64]).repeat([4, 1]);
    let f = importance_depths(&z, &w, &u);
    assert!(finite(&f));
    assert!(min(&f) >= 0.6 && max(&f) <= 1.4);
    let d = f.narrow(1, 1, 63) - f.narrow(1, 0, 63);
    assert!(min(&d) >= 0.0, "inverse CDF of sorted uniforms is sorted");
    // Zero weights (before the +1e-5 floors) give a uniform pdf: samples spread evenly.
    let g = sample_pdf(&z, &Tensor::zeros([4, n - 1], opts), &u);
    assert!(finite(&g));
    let spread = g.get(0) - Tensor::linspace(0.6, 1.4 - 0.8e-7, 64, opts);
    assert!(max(&spread.abs()) < 1e-5, "uniform pdf → linear inverse CDF");
}

#[test]
fn renderer_merges_into_sorted_samples_at_every_pose() {
    let (_vs, g) = small_generator(Kind::Float, 3);
    let cam = CameraConfig::chair();
    let cfg = RenderConfig { num_steps: 8, ..Default::default() };
    let r = Renderer::new(&g, &cam, &cfg).unwrap();
    let z = Tensor::randn([6, 8], (Kind::Float, CPU));
    let lat = g.latents(&z, &z, None).unwrap();
    let poses = Poses::from_angles(
        &[(0.0, 0.0), (PI, 1.0), (1.0, PI), (1.0, -PI), (1e-9, -PI), (PI - 1e-9, 2.0)],
        Kind::Float,
        CPU,
    );
    let rays = Rays::from_poses(&poses, 6, cam.fov_deg);
    let out = tch::no_grad(|| r.render_rays(&lat, &rays, &Noise::default())).unwrap();
    assert!(finite(&out.pixel) && finite(&out.depth) && finite(&out.z));
    let dz = out.z.narrow(2, 1, 15) - out.z.narrow(2, 0, 15);
    assert!(min(&dz) >= 0.0);
}

/// Sampling only occupied bins: one occupied bin, alternating bins and a full ray, with
/// densities from −inf to +inf, give sorted in-range depths and finite weights; a fully
/// occupied ray integrates as the plain one.
#[test]
fn occupied_length_sampling_with_degenerate_occupancy_and_densities() {
    let opts = (Kind::Float, CPU);
    let m = 16;
    let occ = Tensor::zeros([1, 3, m], opts);
    let _ = occ.get(0).get(0).narrow(0, 7, 1).fill_(1.0);
    let _ = occ.get(0).get(1).slice(0, 0, m, 2).fill_(1.0);
    let _ = occ.get(0).get(2).fill_(1.0);
    let o = OccupiedLength::new(&occ, (0.6, 1.4));
    let u = Tensor::rand([1, 3, 12], opts);
    let z = o.stratified(12, Some(&u));
    assert!(finite(&z) && min(&z) >= 0.6 - 1e-6 && max(&z) <= 1.4 + 1e-6, "{z}");
    assert!(min(&(z.narrow(2, 1, 11) - z.narrow(2, 0, 11))) >= 0.0);
    let sigma = Tensor::linspace(-1e4, 1e4, 12, opts).view([1, 1, 12, 1]).repeat([1, 3, 1, 1]);
    let _ = sigma.get(0).get(0).narrow(0, 0, 3).fill_(f64::INFINITY);
    let _ = sigma.get(0).get(1).narrow(0, 3, 3).fill_(f64::NEG_INFINITY);
    let scaled = o.absorb_only_where_occupied(&sigma, &z);
    let w = gdrf_core::render::weights_from_density(&scaled, &z.unsqueeze(-1), 1e10);
    assert!(finite(&w) && min(&w) >= 0.0 && max(&w.sum_dim_intlist(2, false, Kind::Float)) <= 1.0 + 1e-5, "{w}");
    // The full ray has no empty bin: every density is kept.
    assert!(bool::try_from(scaled.get(0).get(2).eq_tensor(&sigma.get(0).get(2)).all()).unwrap());
}

#[test]
fn camera_poles_yaw_wrap_and_extreme_fov() {
    for kind in [Kind::Float, Kind::Double] {
        let poses =
            Poses::from_angles(&[(0.0, 0.0), (PI, 0.0), (0.0, PI), (PI, -PI), (1.0, PI), (1.0, -PI)], kind, CPU);
        let r = cam2world_rotation(&poses);
        assert!(finite(&r));
        // yaw ±π is one camera.
        assert!(max(&(r.get(4) - r.get(5)).abs()) < 1e-6);
        for fov in [1e-4, 1.0, 90.0, 179.0, 179.9999] {
            let rays = Rays::from_poses(&poses, 5, fov);
            assert!(finite(&rays.dirs) && finite(&rays.origins), "fov {fov}");
            let n = rays.dirs.square().sum_dim_intlist(-1, false, kind).sqrt();
            assert!(max(&(n - 1.0).abs()) < 1e-5);
        }
        let d = pixel_directions(3, 1e-4, kind, CPU);
        assert!(max(&(d.select(1, 2) + 1.0).abs()) < 1e-6, "a tiny fov looks straight ahead");
    }
    // Sampled poses stay away from the poles (the release clamps pitch).
    let cam = CameraConfig { v_mean: 0.0, v_std: 1.0, ..CameraConfig::chair() };
    let p = Poses::sample(&cam, 512, Kind::Float, CPU);
    assert!(min(&p.pitch) >= 1e-5 - 1e-9);
}

#[test]
fn siren_layers_with_large_inputs_and_frequencies() {
    let vs = nn::VarStore::new(CPU);
    let sine = SineLayer::new(vs.root() / "s", 3, 16, WeightInit::FirstLayer);
    let film = FilmLayer::new(vs.root() / "f", 3, 16, WeightInit::Frequency(25.0));
    let x = (Tensor::rand([2, 100, 3], (Kind::Float, CPU)) * 20.0 - 10.0).set_requires_grad(true);
    let gamma = Tensor::full([2, 1, 16], 1e3, (Kind::Float, CPU));
    let beta = Tensor::full([2, 1, 16], -1e3, (Kind::Float, CPU));
    for y in [sine.forward(&x), film.forward(&x, &gamma, &beta)] {
        assert!(finite(&y) && max(&y.abs()) <= 1.0);
        let g = Tensor::run_backward(&[y.sum(Kind::Float)], &[&x], false, false).remove(0);
        assert!(finite(&g));
    }
}

#[test]
fn regularisers_at_the_exact_initial_state() {
    // At initialisation the deformation head weight is zero: ∂Δx/∂x = 0 and JᵀJ − I = 0
    // exactly, where a hand-written √Σx² norm has a NaN gradient.
    let (vs, g) = small_generator(Kind::Float, 5);
    let z = Tensor::randn([2, 8], (Kind::Float, CPU));
    let near = Tensor::rand([2, 20, 3], (Kind::Float, CPU)) - 0.5;
    let rest = Tensor::rand([2, 40, 3], (Kind::Float, CPU)) - 0.5;
    let samples = RegSamples { near, rest: Some(rest) };
    for variant in [RegVariant::Release, RegVariant::Paper] {
        let shape = g.shape_from_z(&z, None);
        let t = regularisers(&g, &shape, &samples, variant);
        assert_eq!(t.smoothness.double_value(&[]), 0.0);
        assert_eq!(t.rigidity.double_value(&[]), 0.0);
        let total = t.weighted_sum(&RegConfig::default());
        assert!(finite(&total));
        total.backward();
        assert!(all_grads_finite(&vs), "{variant:?}: non-finite gradient at the initial state");
        for (_, mut v) in vs.variables() {
            if v.grad().defined() {
                v.zero_grad();
            }
        }
    }
    // Normal consistency with zero density gradients on both sides: the template density
    // head and the correction are constant in x.
    tch::no_grad(|| {
        let _ = vs.variables()["template.sigma_head.weight"].shallow_clone().zero_();
    });
    let shape = g.shape_from_z(&z, None);
    let t = regularisers(&g, &shape, &samples, RegVariant::Release);
    assert!((t.normal.double_value(&[]) - 1.0).abs() < 1e-6, "cos(0, 0) counts as 0");
    t.normal.backward();
    assert!(all_grads_finite(&vs));
}

#[test]
fn saturated_discriminator_and_wrapped_poses() {
    let vs = nn::VarStore::new(CPU);
    let d = gdrf_core::rng::with_global_seed(0, || Discriminator::new(&vs.root()));
    tch::no_grad(|| {
        let h = d.head.weight.shallow_clone();
        h.shallow_clone().copy_(&(h * 1e5));
    });
    let real = (Tensor::rand([2, 3, 16, 16], (Kind::Float, CPU)) * 2.0 - 1.0).set_requires_grad(true);
    let o = d.forward(&real, 1.0).unwrap();
    assert!(max(&o.logit.abs()) > 100.0, "the head is saturated");
    let r1 = gan::r1_penalty(&o.logit, &real).unwrap();
    assert!(gan::r1_penalty(&o.logit.detach(), &real.detach()).is_err(), "R1 without a graph is an error, not a crash");
    let total = gan::d_real(&o.logit) + gan::d_fake(&(-&o.logit)) + &r1;
    assert!(finite(&total));
    total.backward();
    assert!(all_grads_finite(&vs));
    let g = gan::g_nonsaturating(&Tensor::from_slice(&[-1e4f32, 1e4]).view([2, 1]), 1);
    assert!(finite(&g));

    // Pose loss across ±π.
    let pred = Tensor::from_slice(&[PI - 1e-3, 1.0]).view([1, 2]).set_requires_grad(true);
    let target = Tensor::from_slice(&[-PI + 1e-3, 1.0]).view([1, 2]);
    let l = gan::pose_loss(&pred, &target);
    assert!(l.double_value(&[]) < 1e-5, "wrap-around is not an error: {l:?}");
    let g = Tensor::run_backward(&[&l], &[&pred], false, false).remove(0);
    assert!(finite(&g) && max(&g.abs()) < 1e-3);
}

/// Relative difference of two tensors of different precision.
fn rel(a: &Tensor, b: &Tensor) -> f64 {
    common::rel_err(&a.to_kind(Kind::Double), &b.to_kind(Kind::Double))
}

#[test]
fn float32_against_float64() {
    // The same weights and noise in both precisions; a deformation head away from its
    // zero initialisation so that every regulariser is non-trivial.
    let (vs64, g64) = small_generator(Kind::Double, 11);
    tch::no_grad(|| {
        let _ = g64.deform.head.weight.shallow_clone().uniform_(-0.02, 0.02);
    });
    let mut vs32 = nn::VarStore::new(CPU);
    let g32 = Generator::new(&vs32.root(), &g64.cfg).unwrap();
    vs32.copy(&vs64).unwrap();
    vs32.float();
    let dvs = nn::VarStore::new(CPU);
    let d32 = Discriminator::new(&dvs.root());
    let mut dvs64 = nn::VarStore::new(CPU);
    let d64 = Discriminator::new(&dvs64.root());
    dvs64.copy(&dvs).unwrap();
    dvs64.double();

    let cam = CameraConfig::chair();
    let cfg = RenderConfig { num_steps: 12, ..Default::default() };
    let (b, res, n) = (2i64, 16i64, 12i64);
    let jitter = Tensor::rand([b, res * res, n], (Kind::Double, CPU));
    let imp = Tensor::rand([b, res * res, n], (Kind::Double, CPU));
    let z = Tensor::randn([b, 8], (Kind::Double, CPU));
    let real = Tensor::rand([b, 3, res, res], (Kind::Double, CPU)) * 2.0 - 1.0;
    let real_pose = Tensor::from_slice(&[1.0f64, 0.3, 1.2, -2.0]).view([2, 2]);
    let reg_rays = Tensor::randint(res * res, [b, 13], (Kind::Int64, CPU));
    let angles = [(1.0, 0.5), (1.2, -2.5)];

    let mut results = Vec::new();
    for (g, d, kind) in [(&g32, &d32, Kind::Float), (&g64, &d64, Kind::Double)] {
        let r = Renderer::new(g, &cam, &cfg).unwrap();
        let zk = z.to_kind(kind);
        let lat: Latents = g.latents(&zk, &zk, None).unwrap();
        let poses = Poses::from_angles(&angles, kind, CPU);
        let noise = Noise { jitter: Some(jitter.to_kind(kind)), importance: Some(imp.to_kind(kind)) };
        let img = r.render_image(&lat, &poses, res, &noise).unwrap();
        let fake = FakeBatch { latents: &lat, poses: &poses, z: None, resolution: res, regions: 1, noise: &noise };
        let at = Schedule { step: 0, alpha: 1.0 };
        let lc = LossConfig::default();
        let gl = generator_pass(&r, d, &fake, Some(&reg_rays), at, &lc).unwrap();
        let dl =
            discriminator_pass(&r, d, &real.to_kind(kind), Some(&real_pose.to_kind(kind)), &fake, at, &lc).unwrap();
        let mut terms = gl.terms;
        terms.extend(dl.terms);
        results.push((img.rgb, img.depth, terms));
    }
    let (a, b64) = (&results[0], &results[1]);
    let mut worst = 0.0f64;
    println!("float32 vs float64 (max |Δ| / max |float64|):");
    for (name, x, y) in [("render rgb", &a.0, &b64.0), ("render depth", &a.1, &b64.1)] {
        let e = rel(x, y);
        println!("  {name:<20} {e:.2e}");
        worst = worst.max(e);
    }
    for ((name, x), (_, y)) in a.2.iter().zip(&b64.2) {
        let e = rel(x, y);
        println!("  {name:<20} {e:.2e}");
        worst = worst.max(e);
    }
    assert!(worst < 1e-4, "float32 drifts from float64 by {worst:e}");
}

/// Central differences in float64 against autograd for a scalar of the parameters.
fn gradcheck(vs: &nn::VarStore, names: &[&str], f: &dyn Fn() -> Tensor, what: &str) {
    let vars = vs.variables();
    for (_, mut v) in vs.variables() {
        if v.grad().defined() {
            v.zero_grad();
        }
    }
    f().backward();
    let eps = 1e-6;
    for name in names {
        let v = &vars[*name];
        let grad = if v.grad().defined() { v.grad() } else { v.zeros_like() };
        let flat = v.view([-1]);
        let n = flat.size()[0];
        for k in [0, n / 3, n - 1] {
            let orig = flat.double_value(&[k]);
            let at = |x: f64| {
                tch::no_grad(|| {
                    let _ = flat.get(k).fill_(x);
                });
                tch::no_grad(f).double_value(&[])
            };
            let fd = (at(orig + eps) - at(orig - eps)) / (2.0 * eps);
            at(orig);
            let ad = grad.view([-1]).double_value(&[k]);
            let err = (fd - ad).abs() / ad.abs().max(fd.abs()).max(1e-3);
            assert!(err < 1e-5, "{what}: ∂/∂{name}[{k}] autograd {ad:e} vs finite difference {fd:e}");
        }
    }
}

#[test]
fn regularisers_pass_a_finite_difference_gradient_check() {
    let (vs, g) = small_generator(Kind::Double, 7);
    tch::no_grad(|| {
        let _ = g.deform.head.weight.shallow_clone().uniform_(-0.05, 0.05);
    });
    let z = Tensor::randn([1, 8], (Kind::Double, CPU));
    let near = (Tensor::rand([1, 6, 3], (Kind::Double, CPU)) - 0.5) * 0.8;
    let rest = (Tensor::rand([1, 6, 3], (Kind::Double, CPU)) - 0.5) * 0.8;
    let samples = RegSamples { near: near.shallow_clone(), rest: Some(rest) };
    let names = [
        "deform.film.0.weight",
        "deform.film.3.bias",
        "deform.head.weight",
        "shape_mapping.3.weight",
        "template.trunk.1.weight",
    ];
    let terms = |sel: fn(&gdrf_core::loss::deform_reg::RegTerms) -> &Tensor, variant| {
        let shape = g.shape_from_z(&z, None);
        let t = regularisers(&g, &shape, &samples, variant);
        sel(&t).shallow_clone()
    };
    for variant in [RegVariant::Release, RegVariant::Paper] {
        gradcheck(&vs, &names, &|| terms(|t| &t.correction, variant), "correction");
        gradcheck(&vs, &names, &|| terms(|t| &t.smoothness, variant), "smoothness");
        gradcheck(&vs, &names, &|| terms(|t| &t.rigidity, variant), "rigidity");
    }
    // Normal consistency has a stop-gradient target: check it with the target frozen.
    let x = near.set_requires_grad(true);
    let shape = g.shape_from_z(&z, None);
    let (dx, dsigma) = g.deform.forward(&x, &shape);
    let target = density_gradient(&x, &(g.template.density(&(&x + &dx)).1 + dsigma));
    let normal = || {
        tch::with_grad(|| {
            let x = x.detach().set_requires_grad(true);
            let shape = g.shape_from_z(&z, None);
            let (dx, _) = g.deform.forward(&x, &shape);
            let x_t = &x + dx;
            let (_, sigma_t) = g.template.density(&x_t);
            normal_distance(&x_t, &sigma_t, &target).mean(Kind::Double)
        })
    };
    gradcheck(&vs, &names, &normal, "normal consistency");
}
