//! The scaled-patch step's side of a step (`[stages.patch]`, EpiGRAF's patch training): the
//! step's patches, one per image, drawn from the annealed scale distribution; the fakes
//! rendered through them, the reals resampled at them, and a discriminator told where
//! each lies.
//!
//! One set of patches serves the whole step, the discriminator's update and the
//! generator's alike, real and fake images alike: the two sides of every verdict then cover
//! the same image positions, and the one-render step's shared fakes need no second set.
use super::reals::RealBatch;
use super::{Stage, Trainer};
use crate::camera::patch::{patch_rays, real_patches, Patch};
use crate::camera::Poses;
use crate::disc::{DiscOutput, Judge};
use crate::render::{assemble_image, Noise, RenderedRays, Renderer};
use crate::rng::{Purpose, RandomSource};
use crate::{Latents, Result};
use tch::{Device, Kind, Tensor};

/// One step's patches: `size²` patches of `of²` images.
#[derive(Debug, Clone)]
pub(super) struct StepPatches {
    pub size: i64,
    pub of: i64,
    /// One per image of the global batch.
    pub all: Vec<Patch>,
}

impl StepPatches {
    /// Images `first .. first + n`'s patches.
    pub fn rows(&self, first: i64, n: i64) -> StepPatches {
        StepPatches { all: self.all[first as usize..(first + n) as usize].to_vec(), ..self.clone() }
    }

    /// `(n, 3)` `[s, ox, oy]` of each patch, as the discriminator is told them.
    pub fn coords(&self, device: Device) -> Tensor {
        let v: Vec<f64> = self.all.iter().flat_map(|p| p.coords()).collect();
        Tensor::from_slice(&v).view([-1, 3]).to_kind(Kind::Float).to_device(device)
    }
}

/// Which images of a batch of `b` share a patch: the members of a minibatch-std group of
/// `group` (images i and i + b/g, as [`crate::disc::minibatch_std`] forms them), so that the
/// group's statistic compares like with like (EpiGRAF's `repeat_interleave`), and with
/// `pairs` the mode-seeking term's pairs (2k, 2k + 1), which must differ in their codes
/// alone. Returns each image's class, classes numbered in order of first image.
pub(super) fn shared_classes(b: i64, group: i64, pairs: bool) -> Vec<usize> {
    let b = b as usize;
    let mut class: Vec<usize> = (0..b).collect();
    fn root(c: &mut [usize], mut i: usize) -> usize {
        while c[i] != i {
            i = c[i];
        }
        i
    }
    fn join(c: &mut [usize], i: usize, j: usize) {
        let (a, z) = (root(c, i), root(c, j));
        c[a.max(z)] = a.min(z);
    }
    if group > 0 {
        let g = (1..=(group as usize).min(b)).rev().find(|g| b.is_multiple_of(*g)).unwrap_or(1);
        for i in 0..b - b / g {
            join(&mut class, i, i + b / g);
        }
    }
    if pairs {
        for k in 0..b / 2 {
            join(&mut class, 2 * k, 2 * k + 1);
        }
    }
    let roots: Vec<usize> = (0..b).map(|i| root(&mut class, i)).collect();
    let mut order: Vec<usize> = Vec::new();
    roots
        .iter()
        .map(|r| match order.iter().position(|o| o == r) {
            Some(k) => k,
            None => {
                order.push(*r);
                order.len() - 1
            }
        })
        .collect()
}

/// A patch of scale P/R + (1 − P/R)·x at the offset fractions `(v, w)` of the room left, from
/// uniforms `u, v, w` ∈ [0, 1): x = 0 (native resolution) where u < `native`, else
/// x ~ Beta(1, β) by its inverse CDF 1 − (1 − u′)^{1/β} of u′ = (u − native) / (1 − native),
/// which is u itself, bit for bit, at `native` = 0.
pub(super) fn draw_patch(min_scale: f64, beta: f64, native: f64, [u, v, w]: [f64; 3]) -> Patch {
    let x = if u < native { 0.0 } else { 1.0 - (1.0 - (u - native) / (1.0 - native)).powf(1.0 / beta) };
    let scale = (min_scale + (1.0 - min_scale) * x).clamp(min_scale, 1.0);
    Patch { scale, offset: ((1.0 - scale) * v, (1.0 - scale) * w) }
}

impl Trainer {
    /// β of the scale distribution at `step` of a patch stage: annealed over the images
    /// seen since the patches began at this resolution and size (over consecutive patch
    /// stages, which may change learning rates or the batch).
    pub(super) fn patch_beta(&self, step: i64) -> f64 {
        let i = self.cfg.stage_index(step);
        let stages = &self.cfg.stages;
        let Some(p) = &stages[i].patch else { return f64::NAN };
        let same = |s: &Stage| s.resolution == stages[i].resolution && s.patch.as_ref().map(|q| q.size) == Some(p.size);
        let first = (0..=i).rev().take_while(|&k| same(&stages[k])).last().unwrap_or(i);
        let images: i64 = (first..=i)
            .map(|k| {
                let end = if k == i { step } else { stages[k + 1].from_step };
                (end - stages[k].from_step) * stages[k].batch_size
            })
            .sum();
        let t = if p.anneal_images == 0 { 1.0 } else { (images as f64 / p.anneal_images as f64).min(1.0) };
        p.beta_start + (p.beta_end - p.beta_start) * t
    }

    /// The patches of `step`'s global batch, `None` for a whole-image stage. A pure function
    /// of (seed, step, config), so every caller and every rank draws the same ones.
    pub(super) fn step_patches(&self, stage: &Stage, step: i64) -> Option<StepPatches> {
        let p = stage.patch.as_ref()?;
        let (b, r) = (stage.batch_size, stage.resolution);
        let pairs = self.cfg.loss.diversity_at(step) > 0.0;
        let class = shared_classes(b, self.cfg.discriminator.minibatch_std_group, pairs);
        let n = class.iter().max().map_or(0, |m| m + 1) as i64;
        let u: Vec<f32> = Vec::try_from(self.rng(step, Purpose::Patches).uniform(&[n, 3]).reshape([-1])).ok()?;
        let (min_scale, beta) = (p.size as f64 / r as f64, self.patch_beta(step));
        let drawn: Vec<Patch> = u
            .chunks(3)
            .map(|c| draw_patch(min_scale, beta, p.native_share, [c[0] as f64, c[1] as f64, c[2] as f64]))
            .collect();
        Some(StepPatches { size: p.size, of: r, all: class.iter().map(|&c| drawn[c]).collect() })
    }

    /// The patches of the step about to run, one per image of the global batch; `None` in a
    /// whole-image stage (tests).
    pub fn patches_now(&self) -> Option<Vec<Patch>> {
        let step = self.progress.step;
        self.step_patches(self.cfg.stage(step), step).map(|p| p.all)
    }

    /// The patches of the images the discriminator judges: all of them where every rank
    /// judges the global batch, else this rank's.
    pub(super) fn judged_patches(&self, all: &StepPatches) -> StepPatches {
        if self.judges_globally() {
            all.clone()
        } else {
            let (first, n) = self.shard(all.all.len() as i64);
            all.rows(first, n)
        }
    }

    /// The real images the discriminator judges at `step` ([`Trainer::judged_real`]) and
    /// their poses: resampled at the step's patches under the scaled-patch step, whole
    /// otherwise.
    pub(super) fn real_seen(&self, real: &RealBatch, stage: &Stage, step: i64) -> Result<(Tensor, Option<Tensor>)> {
        let (images, poses) = self.judged_real(real, step);
        match self.step_patches(stage, step) {
            Some(p) => {
                let p = self.judged_patches(&p);
                Ok((real_patches(&images, &p.all, p.size)?, poses))
            }
            None => Ok((images, poses)),
        }
    }
}

/// Renders `(z, poses, noise)`'s fakes `(B, 3, S, S)` with `renderer`: the stage's whole
/// images (in its bands), or through `patches` (this rank's rows) at their side.
pub(super) fn render_fakes(
    renderer: &Renderer,
    lat: &Latents,
    (poses, noise): (&Poses, &Noise),
    stage: &Stage,
    patches: Option<&StepPatches>,
) -> Result<(Tensor, Vec<RenderedRays>)> {
    match patches {
        None => renderer.render_regions(lat, poses, stage.resolution, stage.regions, noise),
        Some(p) => {
            let rays = patch_rays(poses, &p.all, p.size, p.of, renderer.camera.fov_deg)?;
            let part = renderer.render_rays_chunked(lat, &rays, noise)?;
            Ok((assemble_image(std::slice::from_ref(&part), p.size), vec![part]))
        }
    }
}

/// A discriminator seeing scaled patches at `at: (B, 3)` ([`Judge::judge_patches`]), or
/// whole images where `at` is `None`: what the losses call, unchanged, under either step.
pub(super) struct Placed<'a> {
    pub inner: &'a dyn Judge,
    pub at: Option<Tensor>,
}

impl Judge for Placed<'_> {
    fn judge(&self, img: &Tensor, alpha: f64) -> Result<DiscOutput> {
        match &self.at {
            Some(at) => self.inner.judge_patches(img, alpha, at),
            None => self.inner.judge(img, alpha),
        }
    }
    fn used_parameters(&self, size: i64) -> Result<i64> {
        self.inner.used_parameters(size)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn groups_and_pairs_share_their_patches() {
        assert_eq!(shared_classes(6, 0, false), vec![0, 1, 2, 3, 4, 5]);
        // Groups of 4 in a batch of 8: images i and i + 2 (minibatch_std's view [g, b/g]).
        assert_eq!(shared_classes(8, 4, false), vec![0, 1, 0, 1, 0, 1, 0, 1]);
        assert_eq!(shared_classes(8, 0, true), vec![0, 0, 1, 1, 2, 2, 3, 3]);
        // Both: the campaign's batch of 8 with groups of 4 and pairs draws one patch.
        assert_eq!(shared_classes(8, 4, true), vec![0; 8]);
        // Groups of 2 in 8 (i, i + 4) with pairs: {0, 1, 4, 5} and {2, 3, 6, 7}.
        assert_eq!(shared_classes(8, 2, true), vec![0, 0, 1, 1, 0, 0, 1, 1]);
        // A group size that does not divide the batch shrinks, as minibatch_std's does.
        assert_eq!(shared_classes(6, 4, false), vec![0, 1, 0, 1, 0, 1]);
    }

    #[test]
    fn scales_follow_the_annealed_beta() {
        // u = 0 gives the smallest scale, offsets span the room left exactly.
        let p = draw_patch(0.5, 0.8, 0.0, [0.0, 1.0, 0.0]);
        assert_eq!(p, Patch { scale: 0.5, offset: (0.5, 0.0) });
        // Beta(1, 1) is uniform: x = u.
        let p = draw_patch(0.25, 1.0, 0.0, [0.5, 0.5, 0.5]);
        assert!((p.scale - 0.625).abs() < 1e-15 && (p.offset.0 - 0.1875).abs() < 1e-15);
        // β = 0.001: (1 − 0.9)^1000 rounds to 0, a whole image.
        assert_eq!(draw_patch(0.5, 0.001, 0.0, [0.9, 0.3, 0.3]).scale, 1.0);
        // The inverse CDF: P(x ≤ t) = 1 − (1 − t)^β; its median at β = 0.8 is 1 − ½^{1/0.8}.
        let m = draw_patch(0.0, 0.8, 0.0, [0.5, 0.0, 0.0]).scale;
        assert!((m - (1.0 - 0.5f64.powf(1.25))).abs() < 1e-15);
        for u in [0.0, 0.3, 0.999_999] {
            let p = draw_patch(0.5, 0.8, 0.0, [u, 0.999_999, 0.999_999]);
            p.check(32, 64).unwrap();
        }
    }

    #[test]
    fn a_native_share_mixes_in_native_patches_and_rescales_the_rest() {
        // Below the share: native resolution, offsets as before.
        assert_eq!(draw_patch(0.5, 0.2, 0.25, [0.1, 0.5, 1.0]), Patch { scale: 0.5, offset: (0.25, 0.5) });
        assert_eq!(draw_patch(0.5, 0.2, 0.25, [0.0, 0.0, 0.0]).scale, 0.5);
        // Above it, u′ = (u − q) / (1 − q): u = 0.625 at q = 0.25 is u′ = 0.5, the median
        // 1 − ½^{1/β} of Beta(1, β).
        let m = draw_patch(0.0, 0.8, 0.25, [0.625, 0.0, 0.0]).scale;
        assert!((m - (1.0 - 0.5f64.powf(1.25))).abs() < 1e-15, "{m}");
        // At the share itself u′ = 0: the smallest Beta scale, still native.
        assert_eq!(draw_patch(0.5, 0.8, 0.25, [0.25, 0.0, 0.0]).scale, 0.5);
        // A share of 0 draws exactly what EpiGRAF's law alone draws (the committed runs).
        for u in [0.0f64, 0.123_456_789, 0.5, 0.987_654_321, 0.999_999] {
            let x = 1.0 - (1.0 - u).powf(1.0 / 0.4);
            let want = (0.5 + 0.5 * x).clamp(0.5, 1.0);
            assert_eq!(draw_patch(0.5, 0.4, 0.0, [u, 0.3, 0.7]).scale.to_bits(), want.to_bits());
        }
        // Over many uniforms the native share and the Beta law's tail come out as designed:
        // P(s ≤ 0.6) = q + (1 − q)(1 − 0.8^β), P(s ≥ 0.9) = (1 − q)·0.2^β.
        let (q, beta, n) = (0.25, 0.2, 100_000);
        let scales: Vec<f64> =
            (0..n).map(|i| draw_patch(0.5, beta, q, [(i as f64 + 0.5) / n as f64, 0.0, 0.0]).scale).collect();
        let share = |f: &dyn Fn(f64) -> bool| scales.iter().filter(|s| f(**s)).count() as f64 / n as f64;
        let small = q + (1.0 - q) * (1.0 - 0.8f64.powf(beta));
        let whole = (1.0 - q) * 0.2f64.powf(beta);
        assert!((share(&|s| s <= 0.6) - small).abs() < 1e-4, "{}", share(&|s| s <= 0.6));
        assert!((share(&|s| s >= 0.9) - whole).abs() < 1e-4, "{}", share(&|s| s >= 0.9));
    }
}
