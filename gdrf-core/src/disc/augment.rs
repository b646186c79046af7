//! Differentiable augmentation of every image the discriminator judges (DiffAugment, Zhao
//! et al., "Differentiable Augmentation for Data-Efficient GAN Training", NeurIPS 2020).
//! Reals and fakes, in the discriminator's step and in the generator's, go through the
//! same random transforms, so the discriminator cannot win on a few thousand images by
//! remembering them, and the generator's gradient passes through the transforms. The
//! projected GAN trains with `color`, `translation` and `cutout`.
//!
//! The transforms are DiffAugment's, with its ratios, on images in [−1, 1]:
//! - `color`: brightness + U(−0.5, 0.5), saturation × U(0, 2) about the per-pixel channel
//!   mean, contrast × U(0.5, 1.5) about the image mean (in that order);
//! - `translation`: a shift by a whole number of pixels in [−⌊S/8 + ½⌋, ⌊S/8 + ½⌋] on
//!   each axis, the uncovered border set to the fill;
//! - `cutout`: a square of side ⌊S/2 + ½⌋ set to the fill, centred on a random pixel and
//!   clipped to the image.
//!
//! DiffAugment fills with 0, mid-grey in [−1, 1]; `fill = 1` is white, the background of
//! the procedural datasets and the authors' renders.
//!
//! The draws come from a [`StepRng`] of the step, so a resumed run replays them.
use super::{DiscOutput, Judge};
use crate::rng::{RandomSource, StepRng};
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::cell::RefCell;
use tch::{Kind, Tensor};

/// One of DiffAugment's transforms.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Augmentation {
    Color,
    Translation,
    Cutout,
}

/// Brightness, saturation and contrast with the given factors, each `(B)`:
/// `x + b`, then `(x − mean_c x)·s + mean_c x`, then `(x − mean x)·c + mean x`.
pub fn colour(img: &Tensor, brightness: &Tensor, saturation: &Tensor, contrast: &Tensor) -> Tensor {
    let per = |t: &Tensor| t.to_kind(img.kind()).view([-1, 1, 1, 1]);
    let x = img + per(brightness);
    let m = x.mean_dim(1, true, x.kind());
    let x = (&x - &m) * per(saturation) + &m;
    let m = x.mean_dim(&[1i64, 2, 3][..], true, x.kind());
    (&x - &m) * per(contrast) + &m
}

/// `out[b, :, i, j] = img[b, :, i + dy_b, j + dx_b]`, `fill` where that falls outside.
/// `shifts`: per image (dy, dx), each at most the image side in magnitude.
pub fn translate(img: &Tensor, shifts: &[(i64, i64)], fill: f64) -> Result<Tensor> {
    let (b, h, w) = dims(img)?;
    if shifts.len() as i64 != b {
        return Err(Error::Shape(format!("{} translations for a batch of {b} images", shifts.len())));
    }
    let rows: Vec<Tensor> = shifts
        .iter()
        .enumerate()
        .map(|(i, &(dy, dx))| {
            img.narrow(0, i as i64, 1).pad([w, w, h, h], "constant", fill).narrow(2, h + dy.clamp(-h, h), h).narrow(
                3,
                w + dx.clamp(-w, w),
                w,
            )
        })
        .collect();
    Ok(Tensor::cat(&rows, 0))
}

/// Sets to `fill`, per image, the `size × size` square whose rows start at
/// `centre.0 − size/2` and columns at `centre.1 − size/2` (integer division), clipped to
/// the image.
pub fn cutout(img: &Tensor, centres: &[(i64, i64)], size: i64, fill: f64) -> Result<Tensor> {
    let (b, h, w) = dims(img)?;
    if centres.len() as i64 != b {
        return Err(Error::Shape(format!("{} cutouts for a batch of {b} images", centres.len())));
    }
    let band = |starts: Vec<i64>, n: i64| {
        let lo = Tensor::from_slice(&starts).to_device(img.device()).view([-1, 1]);
        let idx = Tensor::arange(n, (Kind::Int64, img.device())).view([1, -1]);
        (idx.ge_tensor(&lo).logical_and(&idx.lt_tensor(&(lo + size)))).to_kind(img.kind())
    };
    let r = band(centres.iter().map(|c| c.0 - size / 2).collect(), h);
    let c = band(centres.iter().map(|c| c.1 - size / 2).collect(), w);
    let hole = r.view([b, 1, h, 1]) * c.view([b, 1, 1, w]);
    Ok(img * (-&hole + 1.0) + hole * fill)
}

fn dims(img: &Tensor) -> Result<(i64, i64, i64)> {
    match img.size()[..] {
        [b, 3, h, w] => Ok((b, h, w)),
        ref s => Err(Error::Shape(format!("images have shape {s:?}, expected [B, 3, H, W]"))),
    }
}

/// Whole numbers in [lo, hi) from uniforms in [0, 1).
fn integers(rng: &mut dyn RandomSource, n: i64, lo: i64, hi: i64) -> Vec<i64> {
    let u = Vec::<f32>::try_from(rng.uniform(&[n]).to_kind(Kind::Float).to_device(tch::Device::Cpu))
        .expect("a float tensor converts to Vec<f32>");
    u.into_iter().map(|u| (lo + (u as f64 * (hi - lo) as f64).floor() as i64).min(hi - 1)).collect()
}

/// `img: (B, 3, S, S)` through `ops` in DiffAugment's order (colour, translation, cutout,
/// whatever order they are listed in), with draws from `rng`; what translation uncovers
/// and cutout removes becomes `fill`.
pub fn augment(img: &Tensor, ops: &[Augmentation], fill: f64, rng: &mut dyn RandomSource) -> Result<Tensor> {
    let (b, h, w) = dims(img)?;
    let mut x = img.shallow_clone();
    if ops.contains(&Augmentation::Color) {
        let mut u = || rng.uniform(&[b]).to_device(img.device());
        let (br, sa, co) = (u() - 0.5, u() * 2.0, u() + 0.5);
        x = colour(&x, &br, &sa, &co);
    }
    if ops.contains(&Augmentation::Translation) {
        let (sy, sx) = ((h as f64 / 8.0 + 0.5) as i64, (w as f64 / 8.0 + 0.5) as i64);
        let dy = integers(rng, b, -sy, sy + 1);
        let dx = integers(rng, b, -sx, sx + 1);
        x = translate(&x, &dy.into_iter().zip(dx).collect::<Vec<_>>(), fill)?;
    }
    if ops.contains(&Augmentation::Cutout) {
        let size = (h as f64 / 2.0 + 0.5) as i64;
        // DiffAugment's centre range: [0, S + 1 − size mod 2).
        let cy = integers(rng, b, 0, h + (1 - size % 2));
        let cx = integers(rng, b, 0, w + (1 - size % 2));
        x = cutout(&x, &cy.into_iter().zip(cx).collect::<Vec<_>>(), size, fill)?;
    }
    Ok(x)
}

/// A discriminator that augments every image before judging it, drawing from one step's
/// stream: successive judgements (the reals, then the fakes) get successive draws.
pub struct AugmentedJudge<'a> {
    inner: &'a dyn Judge,
    ops: &'a [Augmentation],
    fill: f64,
    rng: RefCell<StepRng>,
}

impl<'a> AugmentedJudge<'a> {
    pub fn new(inner: &'a dyn Judge, ops: &'a [Augmentation], fill: f64, rng: StepRng) -> Self {
        Self { inner, ops, fill, rng: RefCell::new(rng) }
    }
}

impl Judge for AugmentedJudge<'_> {
    fn judge(&self, img: &Tensor, alpha: f64) -> Result<DiscOutput> {
        let x = augment(img, self.ops, self.fill, &mut *self.rng.borrow_mut())?;
        self.inner.judge(&x, alpha)
    }
    /// The patches' coordinates pass through: translation moves a patch's content within
    /// it, as it moves a whole image's.
    fn judge_patches(&self, img: &Tensor, alpha: f64, at: &Tensor) -> Result<DiscOutput> {
        let x = augment(img, self.ops, self.fill, &mut *self.rng.borrow_mut())?;
        self.inner.judge_patches(&x, alpha, at)
    }
    fn used_parameters(&self, size: i64) -> Result<i64> {
        self.inner.used_parameters(size)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Purpose;
    use tch::Device;

    fn ramp(b: i64, s: i64) -> Tensor {
        Tensor::arange(b * 3 * s * s, (Kind::Float, Device::Cpu)).view([b, 3, s, s]) + 1.0
    }

    fn at(t: &Tensor, i: &[i64]) -> f64 {
        t.double_value(i)
    }

    #[test]
    fn translation_moves_pixels_by_whole_steps_and_fills_the_border() {
        let img = ramp(2, 4);
        // 0 is DiffAugment's fill, 1 white; 0.75 is exact in float32.
        for fill in [0.0, 1.0, 0.75] {
            let out = translate(&img, &[(1, -2), (0, 0)], fill).unwrap();
            // Image 0: out[i, j] = img[i + 1, j − 2].
            for c in 0..3 {
                for i in 0..4 {
                    for j in 0..4 {
                        let (si, sj) = (i + 1, j - 2);
                        let inside = (0..4).contains(&si) && (0..4).contains(&sj);
                        let want = if inside { at(&img, &[0, c, si, sj]) } else { fill };
                        assert_eq!(at(&out, &[0, c, i, j]), want, "fill {fill} c {c} i {i} j {j}");
                    }
                }
            }
            assert_eq!(
                Vec::<f32>::try_from(out.get(1).flatten(0, -1)).unwrap(),
                Vec::<f32>::try_from(img.get(1).flatten(0, -1)).unwrap()
            );
        }
    }

    #[test]
    fn cutout_fills_the_clipped_square_and_nothing_else() {
        let img = ramp(2, 4);
        for fill in [0.0, 1.0, 0.75] {
            // Size 2 centred at (0, 3): rows −1..0 → row 0, columns 2..3.
            let out = cutout(&img, &[(0, 3), (2, 2)], 2, fill).unwrap();
            for c in 0..3 {
                for i in 0..4 {
                    for j in 0..4 {
                        let hole0 = i == 0 && (2..4).contains(&j);
                        let hole1 = (1..3).contains(&i) && (1..3).contains(&j);
                        assert_eq!(at(&out, &[0, c, i, j]), if hole0 { fill } else { at(&img, &[0, c, i, j]) });
                        assert_eq!(at(&out, &[1, c, i, j]), if hole1 { fill } else { at(&img, &[1, c, i, j]) });
                    }
                }
            }
        }
    }

    #[test]
    fn colour_factors_act_as_stated() {
        // One pixel (r, g, b) = (0.2, −0.4, 0.5) and one (0, 0, 0).
        let img = Tensor::from_slice(&[0.2f32, 0.0, -0.4, 0.0, 0.5, 0.0]).view([1, 3, 1, 2]);
        let one = |v: f32| Tensor::from_slice(&[v]);
        // Brightness alone.
        let out = colour(&img, &one(0.25), &one(1.0), &one(1.0));
        let want = [0.45f32, 0.25, -0.15, 0.25, 0.75, 0.25];
        for (g, w) in Vec::<f32>::try_from(out.flatten(0, -1)).unwrap().iter().zip(want) {
            assert!((g - w).abs() <= 1e-6, "{g} vs {w}");
        }
        // Saturation 0: every channel becomes the pixel's channel mean (0.1 and 0).
        let out = colour(&img, &one(0.0), &one(0.0), &one(1.0));
        let want = [0.1f32, 0.0, 0.1, 0.0, 0.1, 0.0];
        for (g, w) in Vec::<f32>::try_from(out.flatten(0, -1)).unwrap().iter().zip(want) {
            assert!((g - w).abs() <= 1e-6, "{g} vs {w}");
        }
        // Contrast 0.5 about the image mean 0.05.
        let out = colour(&img, &one(0.0), &one(1.0), &one(0.5));
        let want = [0.125f32, 0.025, -0.175, 0.025, 0.275, 0.025];
        for (g, w) in Vec::<f32>::try_from(out.flatten(0, -1)).unwrap().iter().zip(want) {
            assert!((g - w).abs() <= 1e-6, "{g} vs {w}");
        }
    }

    #[test]
    fn augmentation_replays_from_its_step_and_passes_gradients() {
        let ops = [Augmentation::Color, Augmentation::Translation, Augmentation::Cutout];
        let img = (Tensor::rand([4, 3, 16, 16], (Kind::Float, Device::Cpu)) * 2.0 - 1.0).set_requires_grad(true);
        let draw = |step| StepRng::new(3, step, Purpose::DiscAugment, Kind::Float, Device::Cpu);
        let a = augment(&img, &ops, 0.0, &mut draw(5)).unwrap();
        let b = augment(&img, &ops, 0.0, &mut draw(5)).unwrap();
        let c = augment(&img, &ops, 0.0, &mut draw(6)).unwrap();
        assert!(a.equal(&b), "the same step must give the same augmentation");
        assert!(!a.equal(&c), "another step must give another augmentation");
        // Cutout at 16² removes an 8 × 8 square clipped to the image: at least 4 × 4 pixels
        // of every image are 0 in all three channels after every transform.
        let zero = a.detach().abs().sum_dim_intlist(1, false, Kind::Float).eq(0.0).sum_dim_intlist(
            &[1i64, 2][..],
            false,
            Kind::Int64,
        );
        for n in Vec::<i64>::try_from(zero).unwrap() {
            assert!(n >= 16, "{n} zero pixels");
        }
        // With a white fill the same draws put white where there was 0: the pixels that
        // differ between the two fills are exactly those set to 1 in the second.
        let white = augment(&img, &ops, 1.0, &mut draw(5)).unwrap().detach();
        let differ = white.ne_tensor(&a.detach());
        assert!(bool::try_from(white.masked_select(&differ).eq(1.0).all()).unwrap());
        assert!(bool::try_from(a.detach().masked_select(&differ).eq(0.0).all()).unwrap());
        assert!(differ.sum(Kind::Int64).int64_value(&[]) >= 4 * 16 * 3);
        let g = Tensor::run_backward(&[a.square().sum(Kind::Float)], &[&img], false, false).remove(0);
        assert!(bool::try_from(g.isfinite().all()).unwrap());
        assert!(g.abs().sum(Kind::Float).double_value(&[]) > 0.0);
        // No transforms: the images themselves.
        assert!(augment(&img, &[], 1.0, &mut draw(5)).unwrap().equal(&img));
    }

    #[test]
    fn bad_shapes_are_errors() {
        let img = ramp(2, 4);
        assert!(translate(&img, &[(0, 0)], 0.0).is_err());
        assert!(cutout(&img, &[(0, 0)], 2, 0.0).is_err());
        let e = augment(
            &Tensor::zeros([2, 4, 4], (Kind::Float, Device::Cpu)),
            &[Augmentation::Color],
            0.0,
            &mut crate::rng::TorchRng { kind: Kind::Float, device: Device::Cpu },
        )
        .unwrap_err();
        assert!(e.to_string().contains("[B, 3, H, W]"), "{e}");
    }
}
