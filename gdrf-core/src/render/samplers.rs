//! Depth samplers: stratified coarse depths and hierarchical (importance) depths.
use tch::{Device, Kind, Tensor};

/// Coarse depths `(B, R, N)`: `linspace(start, end, N)` for every ray, plus, when
/// `jitter` `(B, R, N)` uniforms in [0, 1) are given, an offset `(u − ½)·Δ` with
/// Δ = (end − start)/(N − 1). Offsets stay within half a bin, so depths stay sorted.
pub fn stratified_depths(
    shape: (i64, i64),
    n: i64,
    range: (f64, f64),
    jitter: Option<&Tensor>,
    opts: (Kind, Device),
) -> Tensor {
    let (b, r) = shape;
    let z = Tensor::linspace(range.0, range.1, n, opts).view([1, 1, n]).expand([b, r, n], false);
    match jitter {
        Some(u) => {
            let delta = if n > 1 { (range.1 - range.0) / (n - 1) as f64 } else { 0.0 };
            z + (u - 0.5) * delta
        }
        None => z.contiguous(),
    }
}

/// Coarse depths `(B, R, N)` within each ray's own `bounds: (B, R, 2)` = [near, far]:
/// `near + (far − near)·k/(N − 1)`, jittered by `(u − ½)` of a bin when `jitter` is given.
pub fn stratified_in(bounds: &Tensor, n: i64, jitter: Option<&Tensor>) -> Tensor {
    let (near, far) = (bounds.narrow(2, 0, 1), bounds.narrow(2, 1, 1));
    let span = &far - &near;
    let t = Tensor::linspace(0.0, 1.0, n, (bounds.kind(), bounds.device())).view([1, 1, n]);
    let z = &near + &span * t;
    match jitter {
        Some(u) if n > 1 => z + (u - 0.5) * (span / (n - 1) as f64),
        _ => z,
    }
}

/// Importance depths as the release draws them. `z: (M, N)` sorted coarse depths,
/// `weights: (M, N)` coarse integration weights, `u: (M, S)` uniforms in [0, 1).
/// Weights get +1e-5, bins are the N − 1 midpoints, and the first and last weights are
/// dropped; returns `(M, S)`, not sorted, inside [mid_0, mid_{N−2}].
pub fn importance_depths(z: &Tensor, weights: &Tensor, u: &Tensor) -> Tensor {
    let n = z.size()[1];
    let w = weights + 1e-5;
    let mids = (z.narrow(1, 0, n - 1) + z.narrow(1, 1, n - 1)) * 0.5;
    sample_pdf(&mids, &w.narrow(1, 1, n - 2), u)
}

/// Inverse-CDF sampling of a piecewise-constant pdf. `bins: (M, K + 1)` edges,
/// `weights: (M, K)` (non-negative), `u: (M, S)` → `(M, S)`.
///
/// A bin whose cdf step is below 1e-5 is treated as width-less (denominator 1), as in
/// the release, so all-zero and one-hot weights stay finite.
pub fn sample_pdf(bins: &Tensor, weights: &Tensor, u: &Tensor) -> Tensor {
    let (m, k) = (weights.size()[0], weights.size()[1]);
    let s = u.size()[1];
    let w = weights + 1e-5;
    let pdf = &w / w.sum_dim_intlist(-1, true, w.kind());
    let cdf = Tensor::cat(&[pdf.narrow(1, 0, 1).zeros_like(), pdf.cumsum(-1, pdf.kind())], -1);
    let u = u.contiguous();
    let idx = u.searchsorted(&cdf, false, false, "left", None::<Tensor>);
    let below = (&idx - 1).clamp_min(0);
    let above = idx.clamp_max(k);
    let both = Tensor::stack(&[below, above], -1).view([m, 2 * s]);
    let cdf_g = cdf.gather(1, &both, false).view([m, s, 2]);
    let bins_g = bins.gather(1, &both, false).view([m, s, 2]);
    let c0 = cdf_g.select(2, 0);
    let denom = cdf_g.select(2, 1) - &c0;
    let denom = denom.ones_like().where_self(&denom.lt(1e-5), &denom);
    let b0 = bins_g.select(2, 0);
    &b0 + (u - c0) / denom * (bins_g.select(2, 1) - &b0)
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

#[cfg(test)]
mod tests {
    use super::*;

    fn all_finite(t: &Tensor) -> bool {
        bool::try_from(t.isfinite().all()).unwrap()
    }

    #[test]
    fn stratified_depths_stay_sorted_and_near_the_range() {
        let u = Tensor::rand([2, 7, 12], (Kind::Double, Device::Cpu));
        let z = stratified_depths((2, 7), 12, (0.6, 1.4), Some(&u), (Kind::Double, Device::Cpu));
        let d = z.narrow(2, 1, 11) - z.narrow(2, 0, 11);
        assert!(f64::try_from(d.min()).unwrap() >= 0.0);
        let half = 0.8 / 11.0 / 2.0;
        assert!(f64::try_from(z.min()).unwrap() >= 0.6 - half - 1e-12);
        assert!(f64::try_from(z.max()).unwrap() <= 1.4 + half + 1e-12);
    }

    #[test]
    fn degenerate_weights_give_finite_samples_in_range() {
        let opts = (Kind::Float, Device::Cpu);
        let z = Tensor::linspace(0.6, 1.4, 16, opts).view([1, 16]).repeat([3, 1]);
        let w = Tensor::zeros([3, 16], opts);
        let _ = w.get(1).get(7).fill_(1.0); // one-hot
        let _ = w.get(2).fill_(1e30); // huge
        let u = Tensor::rand([3, 16], opts);
        let f = importance_depths(&z, &w, &u);
        assert!(all_finite(&f));
        assert!(f64::try_from(f.min()).unwrap() >= 0.6 && f64::try_from(f.max()).unwrap() <= 1.4);
        // One-hot mass concentrates the samples next to the heavy bin.
        let row = f.get(1);
        let near = row.ge(z.double_value(&[1, 6])).logical_and(&row.le(z.double_value(&[1, 8])));
        assert!(f64::try_from(near.to_kind(Kind::Float).mean(Kind::Float)).unwrap() > 0.9);
    }
}
