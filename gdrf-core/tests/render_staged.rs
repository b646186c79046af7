//! The staged renderer against the dense reference path, on the shipped trained model
//! (real empty space and surfaces): the shape side shaded with every sample gives the
//! reference image; density-first shading stays within its bound while skipping samples;
//! a kept shape side re-shaded with another appearance gives the swapped render.
mod common;

use common::{assert_close, repo_root};
use gdrf_core::camera::{Poses, Rays};
use gdrf_core::checkpoint::load_generator;
use gdrf_core::render::{Noise, Renderer};
use gdrf_core::{Latents, RenderConfig};
use tch::{Device, Kind, Tensor};

struct Case {
    loaded: gdrf_core::checkpoint::LoadedGenerator,
    rays: Rays,
    z: Tensor,
}

fn case() -> Case {
    let path = repo_root().join("models/chairs-tiny/generator.safetensors");
    let loaded =
        load_generator(&path, Device::Cpu, Kind::Float).unwrap_or_else(|e| panic!("the shipped model is needed: {e}"));
    let cam = loaded.header.camera.clone().unwrap();
    let poses = Poses::from_angles(&[(cam.v_mean, 0.4), (cam.v_mean - 0.2, 2.0)], Kind::Float, Device::Cpu);
    let rays = Rays::from_poses(&poses, 24, cam.fov_deg);
    let z = gdrf_core::nn::mapping::seeded_randn(&[3, loaded.generator.cfg.latent_dim as i64], 7);
    Case { loaded, rays, z }
}

fn latents(c: &Case, shape: &[i64], appearance: &[i64]) -> Latents {
    let pick = |i: &[i64]| c.z.index_select(0, &Tensor::from_slice(i));
    tch::no_grad(|| c.loaded.generator.latents(&pick(shape), &pick(appearance), None)).unwrap()
}

#[test]
fn staged_shading_agrees_with_the_reference() {
    let c = case();
    let cam = c.loaded.header.camera.clone().unwrap();
    let rc = RenderConfig { num_steps: 12, jitter: false, ..Default::default() };
    let r = Renderer::new(&c.loaded.generator, &cam, &rc).unwrap();
    let noise = Noise { jitter: None, importance: Some(Tensor::rand([2, 24 * 24, 12], (Kind::Float, Device::Cpu))) };
    let lat = latents(&c, &[0, 1], &[0, 1]);
    let reference = tch::no_grad(|| r.render_rays(&lat, &c.rays, &noise)).unwrap();

    // Every sample shaded: the reference image (same points, same weights).
    let all = r.staged().shape_side(&lat.shape, &c.rays, &noise, 0.0).unwrap();
    assert_eq!(all.kept, all.evaluated);
    assert_close("all samples: pixel", &r.staged().shade(&all, &lat.appearance).unwrap(), &reference.pixel, 1e-6, 1e-5);
    assert_close("opacity", &all.opacity, &reference.opacity, 1e-6, 1e-5);
    assert_close("depth", &all.depth, &reference.depth, 1e-6, 1e-5);

    // Density-first: samples of weight ≤ 1e-3 skipped; each pixel moves by at most the
    // skipped weight, (S samples · 1e-3) · (1 + 2ε).
    let t = 1e-3;
    let side = r.staged().shape_side(&lat.shape, &c.rays, &noise, t).unwrap();
    println!("density-first at {t}: {} of {} samples shaded", side.kept, side.evaluated);
    // On this model about 40 % of the samples weigh less than 1e-3.
    assert!(
        side.kept * 10 < side.evaluated * 9,
        "only {} of {} samples skipped",
        side.evaluated - side.kept,
        side.evaluated
    );
    let bound = 24.0 * t * (1.0 + 2.0 * rc.widen_eps);
    assert_close(
        "density-first pixel",
        &r.staged().shade(&side, &lat.appearance).unwrap(),
        &reference.pixel,
        bound,
        0.0,
    );

    // The shape side of images (0, 1) re-shaded with the appearances of codes (2, 0): the
    // render of those swapped latents.
    let swapped = latents(&c, &[0, 1], &[2, 0]);
    let want = tch::no_grad(|| r.render_rays(&swapped, &c.rays, &noise)).unwrap();
    assert_close("re-shaded pixel", &r.staged().shade(&all, &swapped.appearance).unwrap(), &want.pixel, 1e-6, 1e-5);
    let e = r.staged().shade(&all, &latents(&c, &[0], &[0]).appearance).unwrap_err().to_string();
    assert!(e.contains("1 appearances for a shape side of 2 images"), "{e}");
}

#[test]
fn render_image_takes_the_density_first_option() {
    let c = case();
    let cam = c.loaded.header.camera.clone().unwrap();
    let lat = latents(&c, &[0, 1], &[1, 2]);
    let poses = Poses::from_angles(&[(cam.v_mean, 0.4), (cam.v_mean - 0.2, 2.0)], Kind::Float, Device::Cpu);
    // Explicit importance uniforms: both renders use the same ones whatever else draws from
    // libtorch's generator meanwhile (tests run in parallel threads).
    let u = Tensor::rand([2, 20 * 20, 12], (Kind::Float, Device::Cpu));
    let render = |t: f64| {
        // Small chunks: the staged path must join them as the reference path does.
        let rc = RenderConfig {
            num_steps: 12,
            jitter: false,
            chunk_points: 2000,
            shade_min_weight: t,
            ..Default::default()
        };
        let r = Renderer::new(&c.loaded.generator, &cam, &rc).unwrap();
        r.render_image(&lat, &poses, 20, &Noise { jitter: None, importance: Some(u.shallow_clone()) }).unwrap()
    };
    let reference = render(0.0);
    let staged = render(1e-3);
    // Images are 2·pixel − 1: twice the per-pixel bound.
    let bound = 2.0 * 24.0 * 1e-3 * (1.0 + 2.0 * RenderConfig::default().widen_eps);
    assert_close("image", &staged.rgb, &reference.rgb, bound, 0.0);
    assert_close("opacity", &staged.opacity, &reference.opacity, 1e-6, 1e-5);
    assert_close("depth", &staged.depth, &reference.depth, 1e-6, 1e-5);
    let bad = RenderConfig { shade_min_weight: 1.5, ..Default::default() };
    assert!(bad.validate().unwrap_err().to_string().contains("render.shade_min_weight"));
}
