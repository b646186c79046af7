//! Cross-check of the generator, cameras, samplers, integration, renderer and the inversion's
//! silhouette term against the PyTorch reference (scripts/reference/), in float32 and
//! float64, outputs and gradients.
//!
//! The reference model is created in Python with the release's parameter names and goes
//! through scripts/convert_official_checkpoint.py, so this also tests the converter.
mod common;

use common::{read_tensors, run_python, Report, TempDir};
use gdrf_core::camera::{Poses, Rays};
use gdrf_core::checkpoint::load_generator;
use gdrf_core::field::generator::{FieldOptions, Truncation};
use gdrf_core::invert::{render_with_opacity, silhouette_loss};
use gdrf_core::nn::mapping::seeded_randn;
use gdrf_core::render::sampler::{importance_depths, stratified_depths};
use gdrf_core::render::{composite, CompositeOptions, Noise, Renderer};
use gdrf_core::{CameraConfig, Film, Latents, RenderConfig};
use std::collections::HashMap;
use tch::{Device, Kind, Tensor};

struct Case {
    t: HashMap<String, Tensor>,
    s: serde_json::Value,
}

impl Case {
    fn get(&self, name: &str) -> &Tensor {
        self.t.get(name).unwrap_or_else(|| panic!("case lacks '{name}'"))
    }
    fn want(&self, name: &str) -> &Tensor {
        self.get(&format!("expected.{name}"))
    }
    fn f(&self, key: &str) -> f64 {
        self.s[key].as_f64().unwrap()
    }
    fn i(&self, key: &str) -> i64 {
        self.s[key].as_i64().unwrap()
    }
}

fn crosscheck(dtype: &str, kind: Kind, tol: f64) {
    let dir = TempDir::new(&format!("crosscheck-{dtype}")).unwrap();
    let out = dir.0.to_str().unwrap();
    run_python("reference/crosscheck.py", &["generator", "--out", out, "--dtype", dtype]);
    let case = Case {
        t: read_tensors(&dir.path("case.safetensors")),
        s: serde_json::from_str(&std::fs::read_to_string(dir.path("case.json")).unwrap()).unwrap(),
    };
    let loaded = load_generator(&dir.path("model.safetensors"), Device::Cpu, kind).unwrap();
    let g = &loaded.generator;
    let mut rep = Report::new(&format!("generator cross-check, {dtype}"), tol);

    // Networks.
    let (z_s, z_a) = (case.get("z_s"), case.get("z_a"));
    let shape_raw = g.shape_mapping.forward(z_s);
    let app_raw = g.appearance_mapping.forward(z_a);
    rep.check("mapping M_s (raw γ, β)", &shape_raw, case.want("shape_raw"));
    rep.check("mapping M_a (raw γ, β)", &app_raw, case.want("appearance_raw"));
    rep.check("w_s", &g.shape_w(z_s), case.want("w_s"));
    let shape = Film::from_raw(&shape_raw);
    let app = Film::from_raw(&app_raw);
    let d = g.density(case.get("points"), &shape, FieldOptions::default());
    rep.check("deformation Δx", &d.dx, case.want("field_dx"));
    rep.check("correction Δσ", &d.dsigma, case.want("field_dsigma"));
    rep.check("template feature f_t", &d.feature, case.want("field_feature"));
    rep.check("template σ_t", &d.sigma_t, case.want("field_sigma_t"));
    rep.check("final σ", &d.sigma, case.want("field_sigma"));
    rep.check("colour", &g.colour(&d.feature, case.get("dirs"), &app), case.want("field_rgb"));
    let psi = case.f("psi");
    let trunc = Truncation {
        psi,
        shape_mean: case.get("shape_mean").shallow_clone(),
        appearance_mean: case.get("appearance_mean").shallow_clone(),
    };
    let ts = g.shape_from_z(z_s, Some(&trunc));
    let ta = g.appearance_from_z(z_a, Some(&trunc));
    let ws = Film::from_raw(case.want("shape_raw_trunc"));
    let wa = Film::from_raw(case.want("appearance_raw_trunc"));
    rep.check_all(
        "truncation ψ",
        &[(ts.gamma, ws.gamma), (ts.beta, ws.beta), (ta.gamma, wa.gamma), (ta.beta, wa.beta)],
    );

    // Cameras and rays.
    let poses = Poses { pitch: case.get("ray_pitch").shallow_clone(), yaw: case.get("ray_yaw").shallow_clone() };
    let rays = Rays::from_poses(&poses, case.i("ray_res"), case.f("fov"));
    rep.check("ray origins", &rays.origins, case.want("ray_origins"));
    rep.check("ray directions", &rays.dirs, case.want("ray_dirs"));

    // Samplers.
    let n = case.i("num_steps");
    let range = (case.f("ray_start"), case.f("ray_end"));
    let b = z_s.size()[0];
    let opts = (kind, Device::Cpu);
    let zj = stratified_depths((b, 5), n, range, Some(case.get("strat_jitter")), opts);
    rep.check("stratified depths (jitter)", &zj, case.want("strat_z"));
    rep.check(
        "stratified depths (plain)",
        &stratified_depths((b, 5), n, range, None, opts),
        case.want("strat_z_plain"),
    );
    let fine = importance_depths(case.get("imp_z"), case.get("imp_weights"), case.get("imp_u"));
    rep.check("importance depths", &fine, case.want("imp_fine"));

    // Integration.
    let base = CompositeOptions::default();
    let variants = [
        ("default", base),
        ("lastback", CompositeOptions { last_back: true, white_back: false, ..base }),
        ("forcewhite", CompositeOptions { force_last_white: true, ..base }),
        ("shortfinal", CompositeOptions { delta_final: 0.05, ..base }),
    ];
    for (tag, o) in variants {
        let c = composite(case.get("int_rgb"), case.get("int_sigma"), case.get("int_z"), &o);
        let w = |k: &str| case.want(&format!("int_{tag}_{k}")).shallow_clone();
        rep.check_all(
            &format!("integration ({tag})"),
            &[(c.pixel, w("pixel")), (c.depth, w("depth")), (c.weights, w("weights")), (c.opacity, w("opacity"))],
        );
    }

    // Full renders at two resolutions (chunked inference path, chunks smaller than an image).
    let camera = CameraConfig::chair();
    let config = RenderConfig { num_steps: n as usize, chunk_points: 24 * 37, ..Default::default() };
    let renderer = Renderer::new(g, &camera, &config).unwrap();
    let rposes = Poses { pitch: case.get("render_pitch").shallow_clone(), yaw: case.get("render_yaw").shallow_clone() };
    let resolutions: Vec<i64> = case.s["resolutions"].as_array().unwrap().iter().map(|v| v.as_i64().unwrap()).collect();
    for (k, &res) in resolutions.iter().enumerate() {
        let noise = Noise {
            jitter: Some(case.get(&format!("render{res}_jitter")).shallow_clone()),
            importance: Some(case.get(&format!("render{res}_imp")).shallow_clone()),
        };
        let lat = g.latents(z_s, z_a, None).unwrap();
        let img = renderer.render_image(&lat, &rposes, res, &noise).unwrap();
        let w = |s: &str| case.want(&format!("render{res}_{s}")).shallow_clone();
        rep.check(&format!("render {res}² rgb"), &img.rgb, &w("rgb"));
        rep.check(&format!("render {res}² depth"), &img.depth, &w("depth"));
        rep.check(&format!("render {res}² opacity"), &img.opacity, &w("opacity"));
        let probe = case.get(&format!("render{res}_probe"));
        if k == 0 {
            // Gradients w.r.t. every parameter, rendered as 3 patches (must equal the whole).
            let (img, _) = renderer.render_regions(&lat, &rposes, res, 3, &noise).unwrap();
            rep.check(&format!("render {res}² rgb (3 patches)"), &img, &w("rgb"));
            (img * probe).sum(kind).backward();
            let mut worst = (String::new(), 0.0f64);
            let vars = loaded.vs.variables();
            let mut names: Vec<_> = vars.keys().cloned().collect();
            names.sort();
            for name in names {
                let e = common::rel_err(&vars[&name].grad(), case.want(&format!("grad.{name}")));
                if e > worst.1 {
                    worst = (name, e);
                }
            }
            rep.rows.push((format!("∂/∂params (48, worst {})", worst.0), worst.1));
            // Gradients w.r.t. the inversion features w_s, γ_a, β_a.
            let w_s = g.shape_w(z_s).detach().set_requires_grad(true);
            let a = g.appearance_from_z(z_a, None);
            let gamma = a.gamma.detach().set_requires_grad(true);
            let beta = a.beta.detach().set_requires_grad(true);
            let lat = Latents {
                shape: g.shape_from_w(&w_s, None),
                appearance: Film { gamma: gamma.shallow_clone(), beta: beta.shallow_clone() },
            };
            let (img, _) = renderer.render_regions(&lat, &rposes, res, 1, &noise).unwrap();
            rep.check("render from features", &img, case.want("render_features_rgb"));
            let grads = Tensor::run_backward(&[(img * probe).sum(kind)], &[&w_s, &gamma, &beta], false, false);
            rep.check("∂/∂w_s", &grads[0], case.want("grad_w_s"));
            rep.check("∂/∂γ_a", &grads[1], case.want("grad_gamma_a"));
            rep.check("∂/∂β_a", &grads[2], case.want("grad_beta_a"));
            // The inversion's silhouette term on the first image, through the render with
            // gradients to w_s and the pose.
            let w_s = g.shape_w(&z_s.narrow(0, 0, 1)).detach().set_requires_grad(true);
            let a = g.appearance_from_z(&z_a.narrow(0, 0, 1), None);
            let lat = Latents { shape: g.shape_from_w(&w_s, None), appearance: a };
            let pitch = case.get("render_pitch").narrow(0, 0, 1).detach().set_requires_grad(true);
            let yaw = case.get("render_yaw").narrow(0, 0, 1).detach().set_requires_grad(true);
            let poses = Poses { pitch: pitch.shallow_clone(), yaw: yaw.shallow_clone() };
            let first = |name: &str| Some(case.get(&format!("render{res}_{name}")).narrow(0, 0, 1));
            let noise1 = Noise { jitter: first("jitter"), importance: first("imp") };
            let (_, opacity) = render_with_opacity(&renderer, &lat, &poses, res, &noise1, None, None).unwrap();
            rep.check("silhouette: rendered opacity", &opacity, case.want("sil_opacity"));
            let sil = silhouette_loss(&opacity, case.get("sil_target"));
            rep.check("silhouette term", &sil, case.want("sil_loss"));
            let grads = Tensor::run_backward(&[sil], &[&w_s, &pitch, &yaw], false, false);
            rep.check("silhouette ∂/∂w_s", &grads[0], case.want("grad_sil_w_s"));
            rep.check("silhouette ∂/∂pitch", &grads[1], case.want("grad_sil_pitch"));
            rep.check("silhouette ∂/∂yaw", &grads[2], case.want("grad_sil_yaw"));
        } else {
            let cam = CameraConfig { lock_view_dependence: true, ..camera.clone() };
            let cfg = RenderConfig { force_last_white: true, ..config.clone() };
            let r = Renderer::new(g, &cam, &cfg).unwrap();
            let lat = g.latents(z_s, z_a, Some(&trunc)).unwrap();
            let img = r.render_image(&lat, &rposes, res, &noise).unwrap();
            rep.check(&format!("render {res}² ψ, locked dirs, white last"), &img.rgb, &w("trunc_locked_rgb"));
        }
    }
    let codes: Vec<Tensor> = [0, 1, 42].iter().map(|&s| seeded_randn(&[1, 256], s)).collect();
    rep.check("seed → code (torch.manual_seed)", &Tensor::cat(&codes, 0), case.want("seed_codes"));
    rep.finish();
}

#[test]
fn generator_matches_pytorch_float32() {
    crosscheck("float32", Kind::Float, 1e-4);
}

#[test]
fn generator_matches_pytorch_float64() {
    crosscheck("float64", Kind::Double, 1e-9);
}
