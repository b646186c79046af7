//! What the initialiser learns from: tuples the generator renders (image, w_s, raw
//! appearance, pose) from random codes and poses, cached by their settings, and real images
//! whose poses are known.
use crate::camera::Poses;
use crate::checkpoint::{load_tensors_with, tensors_to_bytes};
use crate::config::{CameraConfig, RenderConfig};
use crate::field::generator::Generator;
use crate::paths::write_atomic;
use crate::progress::Event;
use crate::render::{Noise, Renderer};
use crate::rng::{Purpose, RandomSource, StepRng};
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;
use tch::{Device, Tensor};

use super::InitConfig;

/// What the generator rendered for the initialiser to learn from.
pub struct Tuples {
    /// `(N, 3, R, R)` in [−1, 1].
    pub images: Tensor,
    /// `(N, mapping_hidden)`.
    pub w_s: Tensor,
    /// `(N, 2·L_c·H)`: the raw appearance (f, β).
    pub appearance_raw: Tensor,
    /// `(N, 2)`: pitch, yaw.
    pub poses: Tensor,
}

/// What makes two sets of rendered tuples the same: the generator and the settings they
/// were drawn and rendered with.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct TuplesHeader {
    generator: String,
    resolution: i64,
    samples: usize,
    count: i64,
    seed: u64,
}

const TUPLES_KEY: &str = "gdrf_initialiser_tuples";

impl Tuples {
    fn header(generator_id: &str, cfg: &InitConfig) -> TuplesHeader {
        TuplesHeader {
            generator: generator_id.into(),
            resolution: cfg.resolution,
            samples: cfg.samples,
            count: cfg.count,
            seed: cfg.seed,
        }
    }

    /// Writes the tuples with what they were rendered from (atomically).
    pub fn save(&self, path: &Path, generator_id: &str, cfg: &InitConfig) -> Result<()> {
        let tensors = [
            ("images", &self.images),
            ("w_s", &self.w_s),
            ("appearance_raw", &self.appearance_raw),
            ("poses", &self.poses),
        ]
        .map(|(n, t)| (n.to_string(), t.shallow_clone()));
        let json = serde_json::to_string(&Self::header(generator_id, cfg))?;
        write_atomic(path, &tensors_to_bytes(&tensors, TUPLES_KEY, &json)?)
    }

    /// The tuples in `path` when they were rendered for this generator and `cfg`'s settings;
    /// None when they were not (they are rendered again then).
    pub fn load(path: &Path, generator_id: &str, cfg: &InitConfig, device: Device) -> Result<Option<Self>> {
        let (json, mut t) = load_tensors_with(path, TUPLES_KEY)?;
        let h: TuplesHeader = serde_json::from_str(&json)
            .map_err(|e| Error::Data { path: path.to_path_buf(), reason: format!("tuples: bad header ({e})") })?;
        if h != Self::header(generator_id, cfg) {
            return Ok(None);
        }
        let mut take = |n: &str| {
            t.remove(n)
                .map(|v| v.to_device(device))
                .ok_or_else(|| Error::Data { path: path.to_path_buf(), reason: format!("tuples: no tensor '{n}'") })
        };
        Ok(Some(Self {
            images: take("images")?,
            w_s: take("w_s")?,
            appearance_raw: take("appearance_raw")?,
            poses: take("poses")?,
        }))
    }
}

/// Real images whose poses are known (a dataset's training split).
pub struct RealImages {
    /// `(N, 3, R, R)` in [−1, 1], on white.
    pub images: Tensor,
    /// `(N, 2)`: pitch, yaw.
    pub poses: Tensor,
}

/// Renders `cfg.count` tuples from codes and poses drawn from `cfg.seed` (the same seed gives
/// the same tuples), reporting to `progress` after each batch of 16.
pub fn generate(
    g: &Generator,
    cam: &CameraConfig,
    cfg: &InitConfig,
    progress: &mut dyn FnMut(Event),
) -> Result<Tuples> {
    cfg.validate()?;
    let (kind, device) = g.kind_device();
    let n = cfg.count;
    let z = StepRng::new(cfg.seed, 0, Purpose::InitData, kind, device).normal(&[n, g.cfg.latent_dim as i64]);
    let poses = Poses::sample_from(cam, n, &mut StepRng::new(cfg.seed, 1, Purpose::InitData, kind, device));
    let rc = RenderConfig { num_steps: cfg.samples, jitter: false, ..Default::default() };
    let r = Renderer::new(g, cam, &rc)?;
    let (mut images, mut ws, mut apps) = (Vec::new(), Vec::new(), Vec::new());
    let mut i = 0;
    while i < n {
        let b = 16.min(n - i);
        let zb = z.narrow(0, i, b);
        let (img, w, a) = tch::no_grad(|| -> Result<_> {
            let lat = g.latents(&zb, &zb, None)?;
            let res = cfg.resolution;
            let noise = Noise::midpoints(b, res * res, cfg.samples as i64, device);
            let img = r.render_image(&lat, &poses.narrow(i, b), res, &noise)?.rgb;
            Ok((img, g.shape_w(&zb), g.appearance_raw(&zb)))
        })?;
        images.push(img);
        ws.push(w);
        apps.push(a);
        i += b;
        progress(Event::new("rendering tuples", i as u64, n as u64));
    }
    Ok(Tuples {
        images: Tensor::cat(&images, 0),
        w_s: Tensor::cat(&ws, 0),
        appearance_raw: Tensor::cat(&apps, 0),
        poses: poses.stacked(),
    })
}

/// The training split of the procedural dataset in `dir` at its stored poses, loaded as
/// gdrf-invert loads a photo (on white, the loader's area filter) at `res`; `progress(done)`
/// every 256 images. Its held-out objects are never read.
pub fn load_real_images(dir: &Path, res: i64, device: Device, progress: &mut dyn FnMut(Event)) -> Result<RealImages> {
    use crate::data::{Metadata, Split};
    let meta = Metadata::load(dir)?;
    let train: Vec<_> = meta.images.iter().filter(|r| r.split == Split::Train).collect();
    if train.is_empty() {
        return Err(Error::Data { path: dir.to_path_buf(), reason: "no training-split images".into() });
    }
    let mut images = Vec::with_capacity(train.len());
    for (i, r) in train.iter().enumerate() {
        images.push(crate::invert::photo::load_photo(
            &dir.join(&r.file),
            None,
            crate::invert::photo::Fit::Crop,
            res,
            Device::Cpu,
        )?);
        if (i + 1) % 256 == 0 || i + 1 == train.len() {
            progress(Event::new("real images", i as u64 + 1, train.len() as u64));
        }
    }
    let poses: Vec<f32> = train.iter().flat_map(|r| [r.pitch as f32, r.yaw as f32]).collect();
    Ok(RealImages {
        images: Tensor::cat(&images, 0).to_device(device),
        poses: Tensor::from_slice(&poses).view([-1, 2]).to_device(device),
    })
}
