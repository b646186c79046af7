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

/// The occupied length along rays whose range `[start, end]` is cut into M equal bins,
/// `occ: (B, R, M)` in {0, 1}: s(t) = the occupied part of [start, t]. Samples placed
/// evenly in s lie in occupied bins only, and the occupied length between two samples
/// is the distance that integration should count between them (empty bins hold no
/// density by the grid's promise).
#[derive(Debug)]
pub struct OccupiedLength {
    start: f64,
    bin: f64,
    occ: Tensor,
    /// `(B, R, M + 1)` s at the bin edges.
    cum: Tensor,
}

impl OccupiedLength {
    pub fn new(occ: &Tensor, range: (f64, f64)) -> Self {
        let m = occ.size()[2];
        let bin = (range.1 - range.0) / m as f64;
        let occ = occ.to_kind(Kind::Float);
        let lengths = &occ * bin;
        let cum = Tensor::cat(&[lengths.narrow(2, 0, 1).zeros_like(), lengths.cumsum(2, Kind::Float)], 2);
        Self { start: range.0, bin, occ, cum }
    }

    /// `(B, R, 1)` occupied length of each ray.
    pub fn total(&self) -> Tensor {
        let m = self.occ.size()[2];
        self.cum.narrow(2, m, 1)
    }

    /// s(t) of depths `t: (B, R, S)`; 0 before the range, the total after it.
    pub fn length_at(&self, t: &Tensor) -> Tensor {
        let m = self.occ.size()[2];
        let x = (t.to_kind(Kind::Float) - self.start) / self.bin;
        let j = x.floor().clamp(0.0, (m - 1) as f64);
        let within = (&x - &j).clamp(0.0, 1.0) * self.bin;
        let j = j.to_kind(Kind::Int64);
        self.cum.gather(2, &j, false) + self.occ.gather(2, &j, false) * within
    }

    /// The depth t(s) of occupied lengths `s: (B, R, S)` (sorted or not): inside the
    /// occupied bin that holds s; an s on the border of two occupied runs maps to the
    /// start of the later one, the total to the end of the last.
    pub fn depth_at(&self, s: &Tensor) -> Tensor {
        let m = self.occ.size()[2];
        let s = s.to_kind(Kind::Float).contiguous();
        // Below the total, the bin with cum_j ≤ s < cum_(j+1) is occupied; at the total
        // (and beyond) that search lands in a trailing empty bin or past the last, so the
        // last occupied bin (first cum_(j+1) ≥ s) is taken instead.
        let right = (s.searchsorted(&self.cum, false, true, "right", None::<Tensor>) - 1).clamp(0, m - 1);
        let left = (s.searchsorted(&self.cum, false, false, "left", None::<Tensor>) - 1).clamp(0, m - 1);
        let j = right.where_self(&self.occ.gather(2, &right, false).gt(0.5), &left);
        let within = (&s - self.cum.gather(2, &j, false)).clamp(0.0, self.bin);
        j.to_kind(Kind::Float) * self.bin + within + self.start
    }

    /// N depths `(B, R, N)` spread evenly over each ray's occupied length, from its start
    /// to its end, jittered by `(u − ½)` of a step when `jitter: (B, R, N)` is given.
    pub fn stratified(&self, n: i64, jitter: Option<&Tensor>) -> Tensor {
        let total = self.total();
        let t = Tensor::linspace(0.0, 1.0, n, (Kind::Float, total.device())).view([1, 1, n]);
        let s = &total * t;
        let s = match jitter {
            Some(u) if n > 1 => (s + (u.to_kind(Kind::Float) - 0.5) * (&total / (n - 1) as f64)).clamp_min(0.0),
            _ => s,
        };
        self.depth_at(&s.minimum(&total))
    }

    /// The raw densities `sigma: (B, R, S, 1)` at sorted depths `z: (B, R, S)` rescaled so
    /// that each sample absorbs over the occupied length to its successor, not the whole
    /// distance: softplus(σ') = softplus(σ)·s-distance / t-distance. Samples without an
    /// empty bin before their successor (and the last sample, whose interval is the
    /// release's infinite one) keep σ exactly.
    pub fn absorb_only_where_occupied(&self, sigma: &Tensor, z: &Tensor) -> Tensor {
        let n = z.size()[2];
        if n < 2 {
            return sigma.shallow_clone();
        }
        let s = self.length_at(z);
        let dt = z.narrow(2, 1, n - 1).to_kind(Kind::Float) - z.narrow(2, 0, n - 1).to_kind(Kind::Float);
        let ds = s.narrow(2, 1, n - 1) - s.narrow(2, 0, n - 1);
        // A ratio below one only where part of the interval lies in empty bins.
        let ratio = (&ds / dt.clamp_min(1e-12)).clamp(0.0, 1.0);
        let ratio = Tensor::cat(&[ratio, s.narrow(2, 0, 1).ones_like()], 2).unsqueeze(-1);
        let kind = sigma.kind();
        let wide = sigma.to_kind(Kind::Float);
        // Inverse softplus of y = ratio·softplus(σ): y + log(1 − e^(−y)), finite for y > 0.
        let y = (wide.clamp_max(1e30).softplus() * &ratio).clamp_min(1e-30);
        let scaled = &y + (-(-&y).expm1()).log();
        // Rounding in s reaches a few 1e-6 of a step; an empty bin (half a cell) in an
        // interval of at most the whole range lowers the ratio by far more than 1e-4.
        scaled.where_self(&ratio.lt(1.0 - 1e-4), &wide).to_kind(kind)
    }
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

    /// Two rays over [0.6, 1.4] in 8 bins: occupied bins {1, 2, 5} and {0, 7}.
    fn two_rays() -> OccupiedLength {
        let occ =
            Tensor::from_slice(&[0f32, 1., 1., 0., 0., 1., 0., 0., 1., 0., 0., 0., 0., 0., 0., 1.]).view([1, 2, 8]);
        OccupiedLength::new(&occ, (0.6, 1.4))
    }

    #[test]
    fn occupied_length_maps_depths_both_ways() {
        let o = two_rays();
        let total = o.total().view([2]);
        assert!((total.double_value(&[0]) - 0.3).abs() < 1e-6 && (total.double_value(&[1]) - 0.2).abs() < 1e-6);
        // Depths inside occupied bins survive the round trip; s grows only inside them.
        let t = Tensor::from_slice(&[0.72f32, 0.79, 0.85, 0.61, 1.33, 1.37]).view([1, 2, 3]);
        assert_close(&o.depth_at(&o.length_at(&t)), &t, 1e-6);
        let expect = Tensor::from_slice(&[0.02f32, 0.09, 0.15, 0.01, 0.13, 0.17]).view([1, 2, 3]);
        assert_close(&o.length_at(&t), &expect, 1e-6);
        // A depth in an empty bin has the occupied length before it.
        let gap = Tensor::from_slice(&[1.0f32, 1.0]).view([1, 2, 1]);
        assert_close(&o.length_at(&gap), &Tensor::from_slice(&[0.2f32, 0.1]).view([1, 2, 1]), 1e-6);
        // The ends of the occupied length: the start of the first occupied bin and the end
        // of the last; a border between runs starts the later run.
        let s = Tensor::from_slice(&[0f32, 0.2, 0.3, 0.0, 0.1, 0.2]).view([1, 2, 3]);
        let expect = Tensor::from_slice(&[0.7f32, 1.1, 1.2, 0.6, 1.3, 1.4]).view([1, 2, 3]);
        assert_close(&o.depth_at(&s), &expect, 1e-6);
    }

    #[test]
    fn stratified_samples_lie_in_occupied_bins_only() {
        let o = two_rays();
        let u = Tensor::rand([1, 2, 9], (Kind::Float, Device::Cpu));
        for jitter in [None, Some(&u)] {
            let z = o.stratified(9, jitter);
            let d = z.narrow(2, 1, 8) - z.narrow(2, 0, 8);
            assert!(f64::try_from(d.min()).unwrap() >= 0.0, "not sorted: {z}");
            // A sample on a bin edge belongs to either bin.
            let occ_at = |z: &Tensor| {
                let bin = ((z - 0.6) / 0.1).floor().clamp(0.0, 7.0).to_kind(Kind::Int64);
                o.occ.gather(2, &bin, false)
            };
            let occ = occ_at(&(&z - 1e-5)).maximum(&occ_at(&(&z + 1e-5)));
            assert_eq!(f64::try_from(occ.min()).unwrap(), 1.0, "a sample in an empty bin: {z}");
        }
    }

    /// Rescaled densities at depths t integrate exactly as the raw densities at occupied
    /// lengths s: the empty bins are cut out of the ray.
    #[test]
    fn absorbing_only_where_occupied_is_integrating_in_occupied_length() {
        let o = two_rays();
        let z = o.stratified(12, None);
        let sigma = Tensor::randn([1, 2, 12, 1], (Kind::Float, Device::Cpu)) * 3.0 + 2.0;
        let scaled = o.absorb_only_where_occupied(&sigma, &z);
        let df = 1e10;
        let in_t = crate::render::weights_from_density(&scaled, &z.unsqueeze(-1), df);
        let in_s = crate::render::weights_from_density(&sigma, &o.length_at(&z).unsqueeze(-1), df);
        assert_close(&in_t, &in_s, 1e-5);
        // Samples with no gap before their successor keep their density bit for bit.
        let same = scaled.eq_tensor(&sigma).to_kind(Kind::Float).sum(Kind::Float).double_value(&[]);
        assert!(same >= 18.0, "only {same} of 24 densities kept");
    }

    fn assert_close(a: &Tensor, b: &Tensor, atol: f64) {
        let err = f64::try_from((a - b).abs().max()).unwrap();
        assert!(err <= atol, "max error {err}: {a} vs {b}");
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
