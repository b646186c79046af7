//! Volume integration ("fancy_integration" of the release), kept in float32 or wider.
use tch::{Kind, Tensor};

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CompositeOptions {
    pub white_back: bool,
    pub last_back: bool,
    pub force_last_white: bool,
    pub delta_final: f64,
    pub widen_eps: f64,
}

impl Default for CompositeOptions {
    fn default() -> Self {
        (&crate::RenderConfig::default()).into()
    }
}

impl From<&crate::RenderConfig> for CompositeOptions {
    fn from(c: &crate::RenderConfig) -> Self {
        Self {
            white_back: c.white_back,
            last_back: c.last_back,
            force_last_white: c.force_last_white,
            delta_final: c.delta_final,
            widen_eps: c.widen_eps,
        }
    }
}

/// Integrated quantities along each ray.
#[derive(Debug)]
pub struct Composite {
    /// `(…, 3)`, widened colours composited (on white if `white_back`).
    pub pixel: Tensor,
    /// `(…, 1)`, expected depth Σwz/Σw; the last sample's depth where Σw is 0.
    pub depth: Tensor,
    /// `(…, S, 1)`.
    pub weights: Tensor,
    /// `(…, 1)`, Σw before any `last_back` adjustment.
    pub opacity: Tensor,
}

/// Integration needs at least float32: 1e10 overflows half precision.
pub(crate) fn wide(t: &Tensor) -> Tensor {
    match t.kind() {
        Kind::Half | Kind::BFloat16 => t.to_kind(Kind::Float),
        _ => t.shallow_clone(),
    }
}

/// Weights `(…, S, 1)` from raw densities `sigma: (…, S, 1)` at sorted depths `z: (…, S, 1)`:
/// α_i = 1 − exp(−δ_i·softplus(σ_i)), δ_S = `delta_final`, w_i = α_i Π_{j<i}(1 − α_j + 1e-10).
/// Density alone decides the weights, so importance sampling needs no colour.
pub fn weights_from_density(sigma: &Tensor, z: &Tensor, delta_final: f64) -> Tensor {
    let (alphas, t) = alphas_transmittance(sigma, z, delta_final);
    alphas * t
}

/// The transmittance in front of each sample, Π_{j<i}(1 − α_j + 1e-10), `(…, S, 1)`, as
/// [`weights_from_density`] computes it (early ray termination reads it).
pub fn transmittance(sigma: &Tensor, z: &Tensor, delta_final: f64) -> Tensor {
    alphas_transmittance(sigma, z, delta_final).1
}

fn alphas_transmittance(sigma: &Tensor, z: &Tensor, delta_final: f64) -> (Tensor, Tensor) {
    let (sigma, z) = (wide(sigma), wide(z));
    let s = z.size()[z.dim() - 2];
    let deltas = z.narrow(-2, 1, s - 1) - z.narrow(-2, 0, s - 1);
    let deltas = Tensor::cat(&[deltas, z.narrow(-2, 0, 1).full_like(delta_final)], -2);
    // +inf densities are capped so that a zero-length interval gives 0, not 0·inf = NaN.
    let alphas = -(-(deltas * sigma.clamp_max(1e30).softplus())).exp() + 1.0;
    let shifted = Tensor::cat(&[alphas.narrow(-2, 0, 1).ones_like(), (-&alphas + 1.0) + 1e-10], -2);
    let t = shifted.cumprod(-2, alphas.kind()).narrow(-2, 0, s);
    (alphas, t)
}

/// Integrates colours `rgb: (…, S, 3)` in (0, 1) and raw densities `sigma: (…, S, 1)` at
/// sorted depths `z: (…, S, 1)`.
pub fn composite(rgb: &Tensor, sigma: &Tensor, z: &Tensor, o: &CompositeOptions) -> Composite {
    let z = wide(z);
    let s = z.size()[z.dim() - 2];
    let mut rgb = wide(rgb);
    if o.force_last_white {
        rgb = Tensor::cat(&[rgb.narrow(-2, 0, s - 1), rgb.narrow(-2, s - 1, 1).ones_like()], -2);
    }
    let rgb = rgb * (1.0 + 2.0 * o.widen_eps) - o.widen_eps;
    let mut weights = weights_from_density(sigma, &z, o.delta_final);
    let opacity = weights.sum_dim_intlist(-2, false, weights.kind());
    if o.last_back {
        let last = weights.narrow(-2, s - 1, 1) + (-&opacity + 1.0).unsqueeze(-2);
        weights = Tensor::cat(&[weights.narrow(-2, 0, s - 1), last], -2);
    }
    let mut pixel = (&weights * rgb).sum_dim_intlist(-2, false, weights.kind());
    if o.white_back {
        pixel = (pixel + 1.0) - &opacity;
    }
    let total = weights.sum_dim_intlist(-2, false, weights.kind());
    let weighted = (&weights * &z).sum_dim_intlist(-2, false, weights.kind());
    let far = z.narrow(-2, s - 1, 1).squeeze_dim(-2);
    let tiny = 1e-10;
    let depth = (weighted / total.clamp_min(tiny)).where_self(&total.gt(tiny), &far);
    Composite { pixel, depth, weights, opacity }
}

/// The share `(…, 1)` of each pixel that the background fills: the last sample's weight
/// where `force_last_white` paints it white, and the light left over where `white_back` adds
/// white. Composited on colour `c` instead of white, a pixel is `pixel + share · (c − 1)` (up
/// to the last sample's widening by ε).
pub(crate) fn background_share(weights: &Tensor, opacity: &Tensor, o: &CompositeOptions) -> Tensor {
    let s = weights.size()[weights.dim() - 2];
    let last = match o.force_last_white {
        true => weights.narrow(-2, s - 1, 1).squeeze_dim(-2),
        false => opacity.zeros_like(),
    };
    match o.white_back {
        true => last - opacity + 1.0,
        false => last,
    }
}

/// Images `(B, 3, H, W)` in [−1, 1] composited on white, recomposited on `colours: (B, 3)` in
/// [0, 1] through the share `(B, 1, H, W)` of each pixel the background fills (one minus a
/// real image's alpha; [`background_share`] of a render).
pub(crate) fn on_background(images: &Tensor, share: &Tensor, colours: &Tensor) -> Tensor {
    let b = colours.size()[0];
    images + share * (colours.view([b, 3, 1, 1]) - 1.0) * 2.0
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Device;

    #[test]
    fn empty_rays_are_white_with_far_depth() {
        let opts = (Kind::Float, Device::Cpu);
        let z = Tensor::linspace(0.6, 1.4, 8, opts).view([1, 8, 1]);
        let sigma = Tensor::full([1, 8, 1], -1e4, opts);
        let rgb = Tensor::full([1, 8, 3], 0.2, opts);
        let c = composite(&rgb, &sigma, &z, &CompositeOptions { delta_final: 1.0, ..Default::default() });
        assert!(f64::try_from((c.pixel - 1.0).abs().max()).unwrap() < 1e-6);
        assert!((c.depth.double_value(&[0, 0]) - 1.4).abs() < 1e-6);
        assert_eq!(c.opacity.double_value(&[0, 0]), 0.0);
    }

    #[test]
    fn opaque_first_sample_takes_all_weight() {
        let opts = (Kind::Float, Device::Cpu);
        let z = Tensor::linspace(0.6, 1.4, 8, opts).view([1, 8, 1]);
        let sigma = Tensor::full([1, 8, 1], 1e4, opts);
        let _ = sigma.get(0).get(0).fill_(1e4);
        let rgb = Tensor::full([1, 8, 3], 0.5, opts);
        let c = composite(&rgb, &sigma, &z, &CompositeOptions::default());
        assert!((c.weights.double_value(&[0, 0, 0]) - 1.0).abs() < 1e-6);
        assert!((c.depth.double_value(&[0, 0]) - 0.6).abs() < 1e-6);
        assert!(f64::try_from(c.opacity.max()).unwrap() <= 1.0 + 1e-6);
    }

    /// Recompositing a render on white through [`background_share`] gives exactly the
    /// render whose background (last sample and leftover light) was colour c, for each way
    /// the leftover light is filled.
    #[test]
    fn a_render_on_white_recomposites_on_any_colour() {
        let opts = (Kind::Double, Device::Cpu);
        tch::manual_seed(7);
        // 2 images of 2 × 2 rays, 6 samples each; densities from empty to opaque.
        let z = Tensor::linspace(0.6, 1.4, 6, opts).view([1, 1, 6, 1]).expand([2, 4, 6, 1], false);
        let sigma = Tensor::randn([2, 4, 6, 1], opts) * 3.0 - 2.0;
        let rgb = Tensor::rand([2, 4, 6, 3], opts);
        let colours = Tensor::from_slice(&[0.1f64, 0.7, 0.3, 0.9, 0.0, 0.5]).view([2, 3]);
        let planes = |t: &Tensor| t.permute([0, 2, 1]).reshape([2, -1, 2, 2]);
        let as_image = |pixel: &Tensor| planes(pixel) * 2.0 - 1.0;
        let base = CompositeOptions { force_last_white: true, widen_eps: 0.0, ..Default::default() };
        for (what, o) in [
            ("white_back", CompositeOptions { delta_final: 0.05, ..base }),
            ("white_back, opaque last", base),
            ("last_back", CompositeOptions { white_back: false, last_back: true, delta_final: 0.05, ..base }),
        ] {
            let c = composite(&rgb, &sigma, &z, &o);
            let share = background_share(&c.weights, &c.opacity, &o);
            let got = on_background(&as_image(&c.pixel), &planes(&share), &colours);
            // The same render with the last sample painted c and the leftover light c.
            let painted =
                Tensor::cat(&[rgb.narrow(2, 0, 5), colours.view([2, 1, 1, 3]).expand([2, 4, 1, 3], false)], 2);
            let plain = CompositeOptions { force_last_white: false, white_back: false, ..o };
            let r = composite(&painted, &sigma, &z, &plain);
            let leftover = if o.white_back { -&r.opacity + 1.0 } else { r.opacity.zeros_like() };
            let want = as_image(&(&r.pixel + leftover * colours.view([2, 1, 3])));
            let err = f64::try_from((&got - &want).abs().max()).unwrap();
            assert!(err < 1e-12, "{what}: max error {err}");
            // And the background does show: the images differ from the ones on white.
            assert!(f64::try_from((&got - as_image(&c.pixel)).abs().max()).unwrap() > 0.1, "{what}");
        }
    }
}
