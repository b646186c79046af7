//! Preview grids of the EMA generator, rendered every `sample_interval` steps from codes
//! fixed for the whole run: samples at fixed poses, a swap matrix (rows share shape,
//! columns share appearance; the diagonal is the samples themselves) and the template
//! rows (full / without correction / template only), as the release's status images.
use super::Trainer;
use crate::camera::Poses;
use crate::field::generator::FieldOptions;
use crate::render::{Noise, Renderer};
use crate::rng::{Purpose, RandomSource, StepRng};
use crate::{io, Latents, Result};
use std::path::{Path, PathBuf};
use tch::{Kind, Tensor};

/// The three preview images.
pub struct Previews {
    /// `(yaws · count, 3, S, S)`: one row per yaw offset, one column per code.
    pub samples: Tensor,
    /// `(k · k, 3, S, S)`: row i = shape of code i, column j = appearance of code j.
    pub swap: Tensor,
    /// `(3 · count, 3, S, S)`: rows full, no correction, template only.
    pub template: Tensor,
    pub count: i64,
    pub swap_side: i64,
}

/// The run's fixed preview codes `(count, latent)`.
pub fn preview_codes(t: &Trainer) -> Tensor {
    let n = t.cfg.samples.count.max(t.cfg.samples.swap);
    StepRng::new(t.cfg.seed, 0, Purpose::SampleCodes, Kind::Float, t.device)
        .normal(&[n, t.cfg.generator.latent_dim as i64])
}

/// Renders the previews with the EMA generator at the current stage's sampling.
pub fn render_previews(t: &Trainer) -> Result<Previews> {
    let step = t.progress.step;
    let stage = t.cfg.stage(step);
    let res = if t.cfg.samples.resolution > 0 { t.cfg.samples.resolution } else { stage.resolution };
    let rc = crate::RenderConfig { num_steps: stage.num_steps, jitter: false, ..t.cfg.render.clone() };
    let cam = &t.cfg.camera;
    let gen = &t.ema_generator;
    let z = preview_codes(t);
    let count = t.cfg.samples.count;
    let k = t.cfg.samples.swap.min(z.size()[0]);
    let pose = |yaw: f64| Poses::from_angles(&[(cam.v_mean, cam.h_mean + yaw)], Kind::Float, t.device);
    let first_yaw = t.cfg.samples.yaws[0];
    // No random numbers: previews are a function of the EMA weights alone.
    let noise = Noise::midpoints(1, res * res, stage.num_steps as i64, t.device);
    tch::no_grad(|| {
        let render = |lat: &Latents, i: i64, yaw: f64, opts: FieldOptions| -> Result<Tensor> {
            let mut r = Renderer::new(gen, cam, &rc)?;
            r.field = opts;
            Ok(r.render_image(&lat.narrow(i, 1), &pose(yaw), res, &noise)?.rgb)
        };
        let zc = z.narrow(0, 0, count);
        let lat = gen.latents(&zc, &zc, None)?;
        let mut samples = Vec::new();
        for &yaw in &t.cfg.samples.yaws {
            for i in 0..count {
                samples.push(render(&lat, i, yaw, FieldOptions::default())?);
            }
        }
        let zk = z.narrow(0, 0, k);
        let (shape, appearance) = crate::edit::matrix::swap_pairs(&zk);
        let swap_lat = gen.latents(&shape, &appearance, None)?;
        let swap =
            (0..k * k).map(|i| render(&swap_lat, i, first_yaw, FieldOptions::default())).collect::<Result<Vec<_>>>()?;
        let mut template = Vec::new();
        for opts in [
            FieldOptions::default(),
            FieldOptions { no_correction: true, ..Default::default() },
            FieldOptions { no_deformation: true, no_correction: true, ..Default::default() },
        ] {
            for i in 0..count {
                template.push(render(&lat, i, first_yaw, opts)?);
            }
        }
        Ok(Previews {
            samples: Tensor::cat(&samples, 0),
            swap: Tensor::cat(&swap, 0),
            template: Tensor::cat(&template, 0),
            count,
            swap_side: k,
        })
    })
}

/// Renders the previews and writes `step-NNNNNNNN-{samples,swap,template}.png` and
/// `latest-*.png` into RUN_DIR/samples.
pub fn write_previews(t: &Trainer) -> Result<Vec<PathBuf>> {
    let p = render_previews(t)?;
    let dir = t.run_dir.join(super::run::SAMPLES);
    std::fs::create_dir_all(&dir).map_err(|source| crate::Error::Io { path: dir.clone(), err: source })?;
    let tag = format!("step-{:08}", t.progress.step);
    let mut out = Vec::new();
    for (name, imgs, cols) in
        [("samples", &p.samples, p.count), ("swap", &p.swap, p.swap_side), ("template", &p.template, p.count)]
    {
        let img = io::to_rgb8(&io::grid(imgs, cols), false)?;
        let path = dir.join(format!("{tag}-{name}.png"));
        io::save_png(&path, &img)?;
        io::save_png(&dir.join(format!("latest-{name}.png")), &img)?;
        out.push(path);
    }
    Ok(out)
}

/// Paths of the latest previews of a run directory.
pub fn latest_previews(run_dir: &Path) -> Vec<PathBuf> {
    ["samples", "swap", "template"]
        .iter()
        .map(|n| run_dir.join(super::run::SAMPLES).join(format!("latest-{n}.png")))
        .collect()
}
