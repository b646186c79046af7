//! What a render takes and gives, per ray: the noise that places its samples, the shape
//! side's density samples, the rendered rays (pixels, depths, weights), their colours and
//! costs, and images.
use tch::Tensor;

/// Uniform noise the renderer would otherwise draw itself. Given explicitly, renders are
/// reproducible and can be cross-checked sample for sample.
#[derive(Debug, Default)]
pub struct Noise {
    /// `(B, R, N)` in [0, 1): stratified jitter (used when `RenderConfig::jitter`).
    pub jitter: Option<Tensor>,
    /// `(B, R, N)` in [0, 1): inverse-CDF uniforms of the importance pass.
    pub importance: Option<Tensor>,
}

impl Noise {
    /// No jitter and the importance uniforms (k + ½)/N of every ray `(B, R, N)`: a render that
    /// draws no random number (the same image every time).
    pub fn midpoints(b: i64, r: i64, n: i64, device: tch::Device) -> Noise {
        let u = (Tensor::arange(n, (tch::Kind::Float, device)) + 0.5) / n as f64;
        Noise { jitter: None, importance: Some(u.view([1, 1, n]).expand([b, r, n], false)) }
    }

    /// Rays `[start, start+len)` of images `[b, b+nb)`.
    pub(crate) fn slice(&self, b: i64, nb: i64, start: i64, len: i64) -> Noise {
        let f = |t: &Option<Tensor>| t.as_ref().map(|t| t.narrow(0, b, nb).narrow(1, start, len));
        Noise { jitter: f(&self.jitter), importance: f(&self.importance) }
    }

    /// The rays `idx` of a one-image bundle's noise `(1, R, N)`.
    pub(crate) fn select_rays(&self, idx: &Tensor) -> Noise {
        let f = |t: &Option<Tensor>| t.as_ref().map(|t| t.index_select(1, idx));
        Noise { jitter: f(&self.jitter), importance: f(&self.importance) }
    }
}

/// What the sampler gives: every sample of a bundle with its density and template
/// features (density first, colour not yet known), sorted by depth.
#[derive(Debug)]
pub struct RaySamples {
    /// `(B, R, S)` sorted depths.
    pub z: Tensor,
    /// `(B, R, S, 1)` raw densities, sorted.
    pub sigma: Tensor,
    /// Template features f_t (what colour needs) per pass — `(B, R, N, F)` each, fine then
    /// coarse — in merge order: colour is pointwise, so the training path colours each pass
    /// and sorts 3 channels instead of F.
    pub features: Vec<Tensor>,
    /// `(B, R, S)`: the merged samples' sort permutation.
    pub order: Tensor,
    /// `(B, R, S)` sorted, true where early termination left the sample unevaluated (its
    /// density reads [`super::sampler::SKIPPED_SIGMA`]); `None` when every sample was evaluated.
    pub skipped: Option<Tensor>,
    /// Field queries spent.
    pub evaluated: i64,
}

impl RaySamples {
    /// `(B, R, S, F)` features sorted by depth.
    pub fn sorted_features(&self) -> Tensor {
        gather_samples(&Tensor::cat(&self.features, 2), &self.order)
    }
}

/// Per-ray results of [`Renderer::render_rays`].
#[derive(Debug)]
pub struct RenderedRays {
    /// `(B, R, 3)`, composited colour in about [0, 1] (widened by ε).
    pub pixel: Tensor,
    /// `(B, R, 1)` expected depth.
    pub depth: Tensor,
    /// `(B, R, 1)` accumulated opacity Σw.
    pub opacity: Tensor,
    /// `(B, R, S)` sorted sample depths (S = 2N with importance sampling).
    pub z: Tensor,
    /// `(B, R, S, 1)` integration weights.
    pub weights: Tensor,
    /// `(B, R, 3)` ray origins and unit directions.
    pub origins: Tensor,
    pub dirs: Tensor,
}

impl RenderedRays {
    /// `(B, R, 1)` the share of each ray's light that the object gives, Σ_{i<S} w_i: the
    /// weights of every sample but the last, which lies at the far bound with an unbounded
    /// interval and stands for the background (painted by the generator or composited).
    pub fn object_share(&self) -> Tensor {
        let s = self.weights.size()[2];
        self.weights.narrow(2, 0, s - 1).sum_dim_intlist(2, false, self.weights.kind())
    }

    /// `(B, R, S, 3)` world-space sample points.
    pub fn points(&self) -> Tensor {
        self.origins.unsqueeze(2) + self.dirs.unsqueeze(2) * self.z.unsqueeze(-1)
    }

    /// Joins consecutive chunks of one bundle; a single chunk is passed through as it is
    /// (no copy, no extra node in the graph).
    pub(crate) fn join(mut parts: Vec<RenderedRays>) -> RenderedRays {
        if parts.len() == 1 {
            return parts.remove(0);
        }
        RenderedRays::concat(&parts)
    }

    /// Joins per-region results along the ray axis (the order of the image's rays).
    pub fn concat(parts: &[RenderedRays]) -> RenderedRays {
        let cat = |f: &dyn Fn(&RenderedRays) -> &Tensor| Tensor::cat(&parts.iter().map(f).collect::<Vec<_>>(), 1);
        RenderedRays {
            pixel: cat(&|p| &p.pixel),
            depth: cat(&|p| &p.depth),
            opacity: cat(&|p| &p.opacity),
            z: cat(&|p| &p.z),
            weights: cat(&|p| &p.weights),
            origins: cat(&|p| &p.origins),
            dirs: cat(&|p| &p.dirs),
        }
    }
}

/// A rendered image batch.
#[derive(Debug)]
pub struct Image {
    /// `(B, 3, H, W)` in about [−1, 1].
    pub rgb: Tensor,
    /// `(B, 1, H, W)` expected depth along the ray.
    pub depth: Tensor,
    /// `(B, 1, H, W)` accumulated opacity.
    pub opacity: Tensor,
}

/// Colours of a bundle of rays and what they cost.
#[derive(Debug)]
pub struct RayColours {
    /// `(B, R, 3)` pixels in (0, 1), `(B, R, 1)` expected depth and opacity.
    pub pixel: Tensor,
    pub depth: Tensor,
    pub opacity: Tensor,
    /// Density (Φ + T_σ) and colour (T_c) queries spent.
    pub density_evals: i64,
    pub colour_evals: i64,
}

impl RayColours {
    pub(crate) fn concat(parts: Vec<RayColours>) -> RayColours {
        let cat = |f: &dyn Fn(&RayColours) -> &Tensor| Tensor::cat(&parts.iter().map(f).collect::<Vec<_>>(), 1);
        RayColours {
            pixel: cat(&|p| &p.pixel),
            depth: cat(&|p| &p.depth),
            opacity: cat(&|p| &p.opacity),
            density_evals: parts.iter().map(|p| p.density_evals).sum(),
            colour_evals: parts.iter().map(|p| p.colour_evals).sum(),
        }
    }
}

/// Images `(B, 3, res, res)` in [−1, 1] from per-band results in image order.
pub fn assemble_image(parts: &[RenderedRays], res: i64) -> Tensor {
    let pixels: Vec<Tensor> = parts.iter().map(|p| p.pixel.shallow_clone()).collect();
    assemble(&pixels, res) * 2.0 - 1.0
}

/// Images `(B, C, res, res)` from per-band values `(B, R_k, C)` in image order.
pub fn assemble(bands: &[Tensor], res: i64) -> Tensor {
    let s = bands[0].size();
    let (b, c) = (s[0], s[2]);
    Tensor::cat(bands, 1).permute([0, 2, 1]).reshape([b, c, res, res])
}

/// Sorts samples along the last axis of `z: (B, R, S)`; returns the sorted depths and the
/// permutation `(B, R, S)` to gather the samples' other quantities with.
pub fn sort_depths(z: &Tensor) -> (Tensor, Tensor) {
    z.sort(-1, false)
}

/// Gathers `values: (B, R, S, C)` along the sample axis with `idx: (B, R, S)`.
pub fn gather_samples(values: &Tensor, idx: &Tensor) -> Tensor {
    let c = values.size()[3];
    values.gather(2, &idx.unsqueeze(-1).expand([-1, -1, -1, c], false), false)
}
