//! Sampling only in a ray's occupied cells: its occupied length, the part of the camera's
//! interval in bins an occupancy grid marks, is sampled evenly, and empty stretches between
//! samples count as empty space when integrating.
use super::{jitter_noise, Placement};
use crate::camera::Rays;
use crate::render::rays::Noise;
use tch::{Kind, Tensor};

/// `samples` depths spread evenly over each ray's occupied length ([`Rays::occupied`]), and
/// one more at the camera's far `end` (the release's rays end there, on their infinite
/// last interval); densities integrate over occupied length only.
#[derive(Debug)]
pub struct OccupiedCells {
    pub length: OccupiedLength,
    pub samples: i64,
    pub jitter: bool,
    pub end: f64,
}

impl Placement for OccupiedCells {
    fn depths(&self, rays: &Rays, noise: &Noise) -> Tensor {
        let jitter = jitter_noise(noise, self.jitter, rays, self.samples);
        let s = rays.dirs.size();
        let (kind, device) = (rays.dirs.kind(), rays.dirs.device());
        // As with bounds: the far-end sample ends every ray as the reference's do.
        let end = Tensor::full([s[0], s[1], 1], self.end, (kind, device));
        Tensor::cat(&[self.length.stratified(self.samples, jitter.as_ref()).to_kind(kind), end], 2)
    }

    fn absorb(&self, sigma: &Tensor, z: &Tensor) -> Tensor {
        self.length.absorb_only_where_occupied(sigma, z)
    }

    /// Drawn in occupied length, so that none falls in an empty bin.
    fn importance_depths(&self, w_c: &Tensor, z_c: &Tensor, u: &Tensor) -> Tensor {
        let coords = self.length.length_at(z_c).to_kind(z_c.kind());
        let f = super::importance::pdf_depths(w_c, &coords, u);
        self.length.depth_at(&f).to_kind(z_c.kind())
    }

    /// Termination walks a ray's samples in depth order, which the occupied length's
    /// rescaled densities do not allow.
    fn terminates(&self) -> bool {
        false
    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Device;

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
}
