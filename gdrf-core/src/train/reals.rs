//! The real side of a step: the training images at each resolution (generated and loaded
//! on first use), the epoch permutations that pick each batch, and the backgrounds the
//! discriminator sees them on.
use super::{Stage, Trainer};
use crate::config::Background;
use crate::data::{self, Dataset};
use crate::render::on_background;
use crate::rng::{Purpose, RandomSource, StepRng};
use crate::{Error, Result};
use tch::{Device, Kind, Tensor};

impl Trainer {
    /// Generates the procedural dataset if the config asks for one that is not there yet.
    pub fn prepare_data(&self, progress: &(dyn Fn(crate::progress::Event) + Sync)) -> Result<data::Prepared> {
        self.cfg.data.prepare(self.cfg.threads, progress)
    }

    /// The training images at `res` (loaded through the cache on first use).
    pub fn dataset(&mut self, res: i64) -> Result<&Dataset> {
        if !self.datasets.contains_key(&res) {
            let opts = self.cfg.data.load_options(res as usize, self.cfg.threads);
            let ds = data::load(&self.cfg.data.path, &opts, &|_| {})?;
            if ds.is_empty() {
                return Err(Error::Data {
                    path: self.cfg.data.path.clone(),
                    reason: "the dataset holds no images".into(),
                });
            }
            if self.random_background() && ds.alpha.is_none() {
                return Err(Error::Data {
                    path: self.cfg.data.path.clone(),
                    reason: format!(
                        "no image has a transparent pixel, and generator.background = \"{}\" composites \
                         the real images on random colours through their alpha",
                        self.cfg.generator.background.name()
                    ),
                });
            }
            self.datasets.insert(res, ds);
        }
        Ok(&self.datasets[&res])
    }

    /// Whether the discriminator sees every image on a random colour
    /// ([`Background::Random`], [`Background::Corners`]).
    pub(super) fn random_background(&self) -> bool {
        !self.cfg.generator.background.is_learned()
    }

    /// `n` background colours `(n, 3)` in [0, 1] of (seed, `step`, `purpose`): uniform, or
    /// with [`Background::Corners`] the same draws rounded to the nearest corner.
    pub(super) fn background_colours(&self, step: i64, purpose: Purpose, n: i64) -> Tensor {
        let u = self.rng(step, purpose).uniform(&[n, 3]);
        match self.cfg.generator.background {
            Background::Corners => u.ge(0.5).to_kind(u.kind()),
            _ => u,
        }
    }

    /// Indices of the next `b` real images: consecutive positions in per-epoch random
    /// permutations of the `n` images (each epoch's permutation drawn from the seed).
    pub(super) fn real_indices(&mut self, b: i64, n: i64) -> Vec<i64> {
        (0..b)
            .map(|i| {
                let pos = self.progress.images_seen + i;
                let epoch = pos / n;
                if self.permutation.as_ref().map(|p| (p.0, p.1.len() as i64)) != Some((epoch, n)) {
                    let mut perm: Vec<i64> = (0..n).collect();
                    let mut r =
                        StepRng::new(self.cfg.seed, epoch as u64, Purpose::RealIndices, Kind::Float, Device::Cpu);
                    let u = r.u64s(n as usize);
                    for k in (1..n as usize).rev() {
                        perm.swap(k, (u[k] % (k as u64 + 1)) as usize);
                    }
                    self.permutation = Some((epoch, perm));
                }
                self.permutation.as_ref().unwrap().1[(pos % n) as usize]
            })
            .collect()
    }

    /// The real images of `step`'s global batch at `stage`'s resolution, and their poses
    /// where known (the next `batch_size` positions of the epoch permutations; the counter
    /// moves on in [`Trainer::step`]).
    pub(super) fn real_batch(&mut self, stage: &Stage, step: i64) -> Result<RealBatch> {
        let (b, res) = (stage.batch_size, stage.resolution);
        let n_real = self.dataset(res)?.len() as i64;
        let idx = self.real_indices(b, n_real);
        let ds = &self.datasets[&res];
        let flips: Option<Vec<bool>> =
            ds.flip.map(|_| self.rng(step, Purpose::RealFlips).u64s(b as usize).iter().map(|x| x & 1 == 1).collect());
        let (real, real_poses) = ds.batch(&idx, flips.as_deref())?;
        // The background fills what the alpha leaves.
        let share = self.random_background().then(|| ds.alpha_batch(&idx, flips.as_deref())).flatten();
        Ok(RealBatch {
            on_white: (real.to_device(self.device), real_poses.map(|p| p.to_device(self.device))),
            background_share: share.map(|a| (-a + 1.0).to_device(self.device)),
        })
    }

    /// The real images the discriminator judges, of the global batch `real` (composited on
    /// `step`'s random colours unless the background is [`Background::Learned`]): all of
    /// them where every rank judges the global batch, else this rank's rows.
    pub(super) fn judged_real(&self, real: &RealBatch, step: i64) -> (Tensor, Option<Tensor>) {
        let (images, poses) = &real.on_white;
        let images = match &real.background_share {
            Some(share) => {
                let colours = self.background_colours(step, Purpose::RealBackground, images.size()[0]);
                on_background(images, share, &colours)
            }
            None => images.shallow_clone(),
        };
        if self.judges_globally() {
            (images, poses.as_ref().map(Tensor::shallow_clone))
        } else {
            (self.own_rows(&images, 1), poses.as_ref().map(|p| self.own_rows(p, 1)))
        }
    }
}

/// A step's real images ([`Trainer::real_batch`]): the global batch on white with its poses
/// where known, and with random backgrounds the share `(B, 1, R, R)` of each pixel the
/// background fills (one minus the alpha).
pub(super) struct RealBatch {
    pub(super) on_white: (Tensor, Option<Tensor>),
    pub(super) background_share: Option<Tensor>,
}
