//! Stratified placements: evenly over the camera's interval (the release's coarse
//! samples), or within each ray's own occupied interval.
use super::{jitter_noise, Placement};
use crate::camera::Rays;
use crate::render::rays::Noise;
use tch::{Device, Kind, Tensor};

/// `samples` depths per ray, `linspace` over `range` and jittered within their bins.
#[derive(Debug, Clone, Copy)]
pub struct Stratified {
    pub range: (f64, f64),
    pub samples: i64,
    pub jitter: bool,
}

impl Placement for Stratified {
    fn depths(&self, rays: &Rays, noise: &Noise) -> Tensor {
        let jitter = jitter_noise(noise, self.jitter, rays, self.samples);
        let (b, r) = (rays.dirs.size()[0], rays.num_rays());
        let opts = (rays.dirs.kind(), rays.dirs.device());
        stratified_depths((b, r), self.samples, self.range, jitter.as_ref(), opts)
    }
}

/// `samples` depths per ray within its own `bounds: (B, R, 2)` = [near, far] (an occupancy
/// grid's first and last occupied cell along it), and one more at the camera's far `end`.
#[derive(Debug)]
pub struct OccupiedBounds {
    pub bounds: Tensor,
    pub samples: i64,
    pub jitter: bool,
    pub end: f64,
}

impl Placement for OccupiedBounds {
    fn depths(&self, rays: &Rays, noise: &Noise) -> Tensor {
        let jitter = jitter_noise(noise, self.jitter, rays, self.samples);
        // The release's last interval is infinite (delta_final): whatever density a ray
        // meets at the camera's far end absorbs its remaining light. Rays with their own
        // bounds keep that sample, so that they end as the reference's do.
        let end = self.bounds.narrow(2, 1, 1).clamp_min(self.end);
        Tensor::cat(&[stratified_in(&self.bounds, self.samples, jitter.as_ref()), end], 2)
    }
}

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

#[cfg(test)]
mod tests {
    use super::*;

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
}
