//! The held-out objects (a photo, novel views and their truth) and what scores an
//! inversion on them.
use crate::camera::{Poses, Rays};
use crate::config::RenderConfig;
use crate::data::synth::restyle::Restyle;
use crate::data::synth::{render_object, SynthOptions};
use crate::data::{Metadata, Split};
use crate::edit::Features;
use crate::error::Context;
use crate::eval::fidelity::psnr;
use crate::eval::probe::{structure_classes, Probe};
use crate::invert::framing::Framing;
use crate::invert::photo::{load_photo, prepare_photo, Fit};
use crate::invert::{render_views, Perceptual};
use crate::pretrained::effnet::EfficientNetLite0;
use crate::render::{Noise, Renderer};
use crate::{CameraConfig, Error, Generator, Result};
use tch::{Kind, Tensor};

use super::Options;

pub(super) struct Case {
    pub(super) file: String,
    pub(super) photo: Tensor,
    /// `(1, 1, R, R)` the photo's silhouette (its alpha, or its background's), for the
    /// silhouette term.
    pub(super) silhouette: Option<Tensor>,
    /// With `--restyle`, the photo as it is (`load_photo`, centre-cropped, no background
    /// found, no framing): what `gdrf-invert` compared before it framed photos.
    pub(super) as_is: Option<Tensor>,
    pub(super) pose: (f64, f64),
    /// `(V, 3, R, R)` ground truth, its alpha `(V, 1, R, R)` and the poses.
    pub(super) novel: Tensor,
    pub(super) alpha: Tensor,
    pub(super) novel_poses: Vec<(f64, f64)>,
    /// The perceptual distance's prepared target of each ground-truth view.
    pub(super) targets: Vec<Vec<Tensor>>,
    /// `(1, 4)` the object's true structure classes.
    pub(super) structure: Tensor,
}

/// What scores a set of features on a case.
pub(super) struct Judge<'a> {
    pub(super) g: &'a Generator,
    pub(super) cam: &'a CameraConfig,
    pub(super) probe: &'a Probe,
    pub(super) effnet: &'a EfficientNetLite0,
    pub(super) perceptual: &'a Perceptual<'a>,
    pub(super) res: i64,
    pub(super) samples: usize,
}

pub(super) fn to_tensor(v: &[f32], res: i64, channels: i64) -> Tensor {
    Tensor::from_slice(v).view([res, res, channels]).permute([2, 0, 1]).unsqueeze(0)
}

pub(super) fn mean(v: &Tensor) -> f64 {
    f64::try_from(v.mean(Kind::Double)).unwrap_or(f64::NAN)
}

/// The wrapped absolute angle between two angles, in degrees.
pub(super) fn angle_deg(a: f64, b: f64) -> f64 {
    let d = a - b;
    d.sin().atan2(d.cos()).abs().to_degrees()
}

/// Scores of one inversion state: [input PSNR, novel PSNR, perceptual, IoU, structure].
type Scores = [f64; 5];

impl Judge<'_> {
    /// The opacity in front of the far plane of `f` at `poses`, `(V, 1, R, R)`: the weights
    /// of every sample but the last, which paints the background.
    fn foreground(&self, f: &Features, poses: &[(f64, f64)]) -> Result<Tensor> {
        let rc = RenderConfig { num_steps: self.samples, jitter: false, ..Default::default() };
        let r = Renderer::new(self.g, self.cam, &rc)?;
        let (kind, device) = self.g.kind_device();
        let k = poses.len() as i64;
        let one = crate::edit::latents(self.g, f, f, None);
        let rep = |t: &Tensor| t.repeat([k, 1]);
        let lat = crate::Latents {
            shape: crate::nn::film::Film { gamma: rep(&one.shape.gamma), beta: rep(&one.shape.beta) },
            appearance: crate::nn::film::Film { gamma: rep(&one.appearance.gamma), beta: rep(&one.appearance.beta) },
        };
        let rays = Rays::from_poses(&Poses::from_angles(poses, kind, device), self.res, self.cam.fov_deg);
        let noise = Noise::midpoints(k, self.res * self.res, self.samples as i64, device);
        let out = tch::no_grad(|| r.render_rays(&lat, &rays, &noise))?;
        let front = out.object_share().to_kind(Kind::Float);
        Ok(front.view([k, self.res, self.res, 1]).permute([0, 3, 1, 2]))
    }

    pub(super) fn score(&self, f: &Features, case: &Case, at: (f64, f64)) -> Result<Scores> {
        let (g, cam) = (self.g, self.cam);
        let input = render_views(g, cam, f, &[at], self.res, self.samples)?;
        let novel = render_views(g, cam, f, &case.novel_poses, self.res, self.samples)?;
        let mut perceptual = 0.0;
        for (i, target) in case.targets.iter().enumerate() {
            perceptual += mean(&(self.perceptual.to_target)(&novel.narrow(0, i as i64, 1), target)?);
        }
        let fg = self.foreground(f, &case.novel_poses)?.gt(0.5);
        let truth = case.alpha.gt(0.5);
        let inter = fg.logical_and(&truth).sum_dim_intlist([1i64, 2, 3].as_slice(), false, Kind::Float);
        let union = fg.logical_or(&truth).sum_dim_intlist([1i64, 2, 3].as_slice(), false, Kind::Float);
        let iou = inter / union.clamp_min(1.0);
        let classes = self.probe.predict(Some(self.effnet), &novel)?.classes;
        let agree = classes.eq_tensor(&case.structure.to_device(classes.device())).to_kind(Kind::Float);
        Ok([
            mean(&psnr(&input, &case.photo)?),
            mean(&psnr(&novel, &case.novel)?),
            perceptual / case.targets.len() as f64,
            mean(&iou),
            mean(&agree),
        ])
    }
}

/// One (checkpoint, object, seed) measurement.
#[derive(Clone, Copy, Default)]
pub(super) struct Cell {
    pub(super) seconds: f64,
    pub(super) scores: Scores,
    pub(super) pitch_err: f64,
    pub(super) yaw_err: f64,
}

/// The folder of the restyled photos of output stem `out` (`--restyle`).
pub(super) fn photos_dir(out: &std::path::Path) -> std::path::PathBuf {
    let mut name = out.file_name().unwrap_or_default().to_os_string();
    name.push("-photos");
    out.with_file_name(name)
}

/// The held-out objects, their photos (the dataset's, or restyled with `--restyle`)
/// prepared as `gdrf-invert PHOTO` prepares them (their silhouette, framed by `framing`).
pub(super) fn load_cases(
    a: &Options,
    res: i64,
    dev: tch::Device,
    perceptual: &Perceptual,
    framing: Option<&Framing>,
) -> Result<Vec<Case>> {
    let meta = Metadata::load(&a.dataset)?;
    let mut opts = meta.options.clone();
    opts.resolution = res as usize;
    // With each image's index in the dataset: the restyled photo's random stream.
    let held: Vec<_> =
        meta.images.iter().enumerate().filter(|(_, r)| r.split == Split::HeldOut).skip(a.skip).take(a.images).collect();
    if held.len() < a.images {
        return Err(Error::Invalid(format!(
            "{} has {} held-out images after --skip {}, --images asks for {}",
            a.dataset.display(),
            held.len(),
            a.skip,
            a.images
        )));
    }
    if a.restyle.is_some() {
        let dir = photos_dir(&a.out);
        std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let mut cases = Vec::new();
    for &(index, r) in &held {
        let (file, restyled) = match a.restyle {
            None => (a.dataset.join(&r.file), false),
            Some(seed) => {
                // The object at the photo's pose, rendered at 128² and restyled.
                let big = SynthOptions { resolution: 128, supersample: 2, ..opts.clone() };
                let rendered = render_object(&r.shape, &r.appearance, r.pitch, r.yaw, &big)?;
                let stem = std::path::Path::new(&r.file).file_stem().unwrap_or_default().to_string_lossy().into_owned();
                let path = photos_dir(&a.out).join(format!("{stem}.jpg"));
                crate::paths::write_atomic(&path, &Restyle::draw(seed, index as u64).photo(&rendered)?)?;
                (path, true)
            }
        };
        let photo = prepare_photo(&file, None, Fit::Auto, framing, res, dev)?;
        let as_is = restyled.then(|| load_photo(&file, None, Fit::Crop, res, dev)).transpose()?;
        let novel_poses: Vec<(f64, f64)> =
            (1..=a.views).map(|k| (r.pitch, r.yaw + std::f64::consts::TAU * k as f64 / (a.views + 1) as f64)).collect();
        let (mut novel, mut alpha) = (Vec::new(), Vec::new());
        for p in &novel_poses {
            let out = render_object(&r.shape, &r.appearance, p.0, p.1, &opts)?;
            novel.push(to_tensor(&out.rgb, res, 3) * 2.0 - 1.0);
            alpha.push(to_tensor(&out.alpha, res, 1));
        }
        let novel = Tensor::cat(&novel, 0).to_device(dev);
        let targets = (0..a.views as i64)
            .map(|i| tch::no_grad(|| (perceptual.target)(&novel.narrow(0, i, 1))))
            .collect::<Result<Vec<_>>>()?;
        cases.push(Case {
            file: r.file.clone(),
            photo: photo.rgb,
            silhouette: photo.silhouette,
            as_is,
            pose: (r.pitch, r.yaw),
            novel,
            alpha: Tensor::cat(&alpha, 0).to_device(dev),
            novel_poses,
            targets,
            structure: Tensor::from_slice(&structure_classes(&r.shape)?).view([1, 4]),
        });
    }
    Ok(cases)
}

/// One row of the figure, `(3, R, 10·R)`: photo | reconstruction | novel views | their
/// ground truth.
pub(super) fn figure_row(j: &Judge, f: &Features, case: &Case, at: (f64, f64)) -> Result<Tensor> {
    let recon = render_views(j.g, j.cam, f, &[at], j.res, j.samples)?;
    let novel = render_views(j.g, j.cam, f, &case.novel_poses, j.res, j.samples)?;
    let tiles = Tensor::cat(&[case.photo.to_device(recon.device()), recon, novel, case.novel.shallow_clone()], 0);
    Ok(crate::io::grid(&tiles, tiles.size()[0]))
}
