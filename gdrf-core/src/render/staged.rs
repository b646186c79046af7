//! The renderer in stages for inference: the density pass builds the **shape side** of a
//! ray bundle — depths, weights, opacity and the template features of the samples that
//! carry weight, packed with their image and ray indices — and **shading** runs the colour
//! branch on those samples only, for any appearance. Density never depends on the
//! appearance code, so a shape side can be kept and re-shaded (appearance edits), and
//! samples whose weight is at most `min_weight` are never shaded (density-first): the
//! pixel changes by at most `min_weight · (skipped samples) · (1 + 2ε)`.
use super::composite::composite;
use super::rays::{Noise, RayColours};
use super::setup::Setup;
use crate::camera::Rays;
use crate::field::RadianceField;
use crate::nn::film::Film;
use crate::Latents;
use crate::{Error, Result};
use tch::{Kind, Tensor};

/// The shape side of `B` images of `R` rays each.
#[derive(Debug)]
pub struct ShapeSide {
    pub batch: i64,
    pub rays: i64,
    /// `(P,)` image index and `(P,)` ray index of each kept sample.
    pub image: Tensor,
    pub ray: Tensor,
    /// `(P, 1)` integration weights (after `last_back`).
    pub weights: Tensor,
    /// `(P, F)` template features and `(P, 3)` view directions of the kept samples.
    pub features: Tensor,
    pub dirs: Tensor,
    /// `(P,)` true where the sample is its ray's last (`force_last_white` paints it white).
    pub last: Tensor,
    /// `(B, R, 1)` opacity Σw (before `last_back`) and expected depth, from all samples.
    pub opacity: Tensor,
    pub depth: Tensor,
    /// Samples the density pass evaluated, and how many of them are kept for shading.
    pub evaluated: i64,
    pub kept: i64,
}

/// The staged path, a part of a renderer ([`Renderer::staged`]).
pub struct Staged<'a, F: RadianceField> {
    pub setup: Setup<'a, F>,
}

impl<F: RadianceField> Staged<'_, F> {
    /// The density pass over rays `(B, R, 3)` (no gradients), keeping the samples whose
    /// weight exceeds `min_weight` (every sample when it is ≤ 0).
    pub fn shape_side(&self, shape: &Film, rays: &Rays, noise: &Noise, min_weight: f64) -> Result<ShapeSide> {
        if !min_weight.is_finite() {
            return Err(Error::Invalid(format!("min_weight is {min_weight}, expected a finite weight threshold")));
        }
        tch::no_grad(|| {
            let d = self.setup.sample(shape, rays, noise)?;
            let s = d.z.size();
            let (b, r, n) = (s[0], s[1], s[2]);
            // Integration without colour: the weights, opacity and depth of composite().
            let c = composite(
                &d.sigma.zeros_like().expand([b, r, n, 3], false),
                &d.sigma,
                &d.z.unsqueeze(-1),
                &self.setup.composite_options(),
            );
            let w = c.weights.view([b * r * n]);
            let keep = if min_weight > 0.0 { w.gt(min_weight) } else { w.ones_like().to_kind(Kind::Bool) };
            // Samples early termination skipped carry no light and have no feature.
            let keep = match &d.skipped {
                Some(skipped) => keep.logical_and(&skipped.reshape([b * r * n]).logical_not()),
                None => keep,
            };
            let flat = keep.nonzero().view([-1]);
            let dirs = self.setup.sample_dirs(&rays.dirs, n).view([b * r * n, 3]);
            let feature = d.sorted_features();
            let f = feature.size()[3];
            Ok(ShapeSide {
                batch: b,
                rays: r,
                image: flat.divide_scalar_mode(r * n, "floor"),
                ray: flat.remainder(r * n).divide_scalar_mode(n, "floor"),
                weights: w.index_select(0, &flat).unsqueeze(-1),
                features: feature.view([b * r * n, f]).index_select(0, &flat),
                dirs: dirs.index_select(0, &flat),
                last: flat.remainder(n).eq(n - 1),
                opacity: c.opacity,
                depth: c.depth,
                evaluated: d.evaluated,
                kept: flat.size()[0],
            })
        })
    }

    /// Density-first rendering of rays `(B, R, 3)` in chunks of about `chunk_points`
    /// samples, shading only the samples whose weight exceeds `shade_min_weight`.
    pub(crate) fn render_chunked(&self, latents: &Latents, rays: &Rays, noise: &Noise) -> Result<RayColours> {
        let sides = self.shape_sides(&latents.shape, rays, noise, self.setup.config.shade_min_weight)?;
        let parts = sides
            .into_iter()
            .map(|side| {
                Ok(RayColours {
                    pixel: self.shade(&side, &latents.appearance)?,
                    depth: side.depth,
                    opacity: side.opacity,
                    density_evals: side.evaluated,
                    colour_evals: side.kept,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(RayColours::concat(parts))
    }

    /// The shape side of rays `(B, R, 3)` in ray chunks of about `chunk_points` samples (so
    /// that any image fits in bounded memory), to keep and shade with [`Self::shade_chunks`].
    pub fn shape_sides(&self, shape: &Film, rays: &Rays, noise: &Noise, min_weight: f64) -> Result<Vec<ShapeSide>> {
        let b = rays.dirs.size()[0];
        self.setup.in_chunks(rays, self.setup.config.samples_per_ray() as i64, |start, len| {
            self.shape_side(shape, &rays.narrow(start, len), &noise.slice(0, b, start, len), min_weight)
        })
    }

    /// Pixels `(B, R, 3)` of kept shape sides (in ray order) under `appearance`.
    pub fn shade_chunks(&self, sides: &[ShapeSide], appearance: &Film) -> Result<Tensor> {
        let parts = sides.iter().map(|s| self.shade(s, appearance)).collect::<Result<Vec<_>>>()?;
        Ok(Tensor::cat(&parts, 1))
    }

    /// Colours `(B, R, 3)` of a shape side under `appearance` (one row per image): the
    /// colour branch on the kept samples only, composited as [`composite`] does.
    pub fn shade(&self, side: &ShapeSide, appearance: &Film) -> Result<Tensor> {
        if appearance.batch_size() != side.batch {
            return Err(Error::Shape(format!(
                "{} appearances for a shape side of {} images",
                appearance.batch_size(),
                side.batch
            )));
        }
        let o = self.setup.composite_options();
        tch::no_grad(|| {
            let (kind, device) = (side.weights.kind(), side.weights.device());
            let mut rgb = Tensor::zeros([side.kept, 3], (kind, device));
            for i in 0..side.batch {
                let sel = side.image.eq(i).nonzero().view([-1]);
                if sel.size()[0] == 0 {
                    continue;
                }
                let feature = side.features.index_select(0, &sel).unsqueeze(0);
                let dirs = side.dirs.index_select(0, &sel).unsqueeze(0);
                let c = self
                    .setup
                    .generator
                    .radiance(&feature, &dirs, &appearance.narrow(i, 1))
                    .squeeze_dim(0)
                    .to_kind(kind);
                rgb = rgb.index_copy(0, &sel, &c);
            }
            if o.force_last_white {
                rgb = rgb.ones_like().where_self(&side.last.unsqueeze(-1), &rgb);
            }
            let rgb = rgb * (1.0 + 2.0 * o.widen_eps) - o.widen_eps;
            let target = &side.image * side.rays + &side.ray;
            let pixel = Tensor::zeros([side.batch * side.rays, 3], (kind, device)).index_add(
                0,
                &target,
                &(&side.weights * rgb),
            );
            let mut pixel = pixel.view([side.batch, side.rays, 3]);
            if o.white_back {
                pixel = (pixel + 1.0) - &side.opacity;
            }
            Ok(pixel)
        })
    }
}
