//! Camera poses, their distributions, look-at and ray generation (the release's pi-GAN
//! conventions: camera on the unit sphere looking at the origin, OpenGL axes).
pub mod patch;

use crate::config::{CameraConfig, PoseDistribution};
use crate::rng::{RandomSource, TorchRng};
use std::f64::consts::PI;
use tch::{Device, Kind, Tensor};

/// Camera poses: pitch φ (polar angle from +y) and yaw θ, each `(B, 1)`, radians.
#[derive(Debug)]
pub struct Poses {
    pub pitch: Tensor,
    pub yaw: Tensor,
}

impl Poses {
    /// Explicit poses `(pitch, yaw)` in radians; no clamping (poles are handled by the
    /// look-at construction).
    pub fn from_angles(angles: &[(f64, f64)], kind: Kind, device: Device) -> Self {
        let p: Vec<f64> = angles.iter().map(|a| a.0).collect();
        let y: Vec<f64> = angles.iter().map(|a| a.1).collect();
        let col = |v: &[f64]| Tensor::from_slice(v).view([-1, 1]).to_kind(kind).to_device(device);
        Self { pitch: col(&p), yaw: col(&y) }
    }

    /// Draws `n` poses from the configured distribution with libtorch's generator (the
    /// release's sampling path, which clamps φ to [1e-5, π − 1e-5]).
    pub fn sample(cam: &CameraConfig, n: i64, kind: Kind, device: Device) -> Self {
        Self::sample_from(cam, n, &mut TorchRng { kind, device })
    }

    /// Draws `n` poses from the configured distribution with the numbers of `src`.
    pub fn sample_from(cam: &CameraConfig, n: i64, src: &mut dyn RandomSource) -> Self {
        let mut sym = || (src.uniform(&[n, 1]) - 0.5) * 2.0;
        let (yaw, pitch) = match cam.distribution {
            PoseDistribution::Uniform => {
                let yaw = sym() * cam.h_std + cam.h_mean;
                (yaw, sym() * cam.v_std + cam.v_mean)
            }
            PoseDistribution::Normal => {
                let yaw = src.normal(&[n, 1]) * cam.h_std + cam.h_mean;
                (yaw, src.normal(&[n, 1]) * cam.v_std + cam.v_mean)
            }
            PoseDistribution::SphericalUniform => {
                let yaw = sym() * cam.h_std + cam.h_mean;
                let v = (sym() * (cam.v_std / PI) + cam.v_mean / PI).clamp(1e-5, 1.0 - 1e-5);
                (yaw, (v * -2.0 + 1.0).acos())
            }
            PoseDistribution::Fixed => {
                let like = src.uniform(&[n, 1]);
                (like.full_like(cam.h_mean), like.full_like(cam.v_mean))
            }
        };
        Self { pitch: pitch.clamp(1e-5, PI - 1e-5), yaw }
    }

    /// `(B, 2)` = `[pitch, yaw]`, the target of the discriminator's pose head.
    pub fn stacked(&self) -> Tensor {
        Tensor::cat(&[&self.pitch, &self.yaw], 1)
    }

    /// The inverse of [`Self::stacked`]: poses from `(B, 2)` = `[pitch, yaw]` (the
    /// datasets' real poses).
    pub fn from_stacked(t: &Tensor) -> Self {
        Self { pitch: t.narrow(1, 0, 1), yaw: t.narrow(1, 1, 1) }
    }

    pub fn len(&self) -> i64 {
        self.pitch.size()[0]
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn narrow(&self, start: i64, len: i64) -> Self {
        Self { pitch: self.pitch.narrow(0, start, len), yaw: self.yaw.narrow(0, start, len) }
    }

    /// Pose 2k repeated at 2k + 1 (see [`rows_in_pairs`]).
    pub fn in_pairs(&self) -> Self {
        Self { pitch: rows_in_pairs(&self.pitch), yaw: rows_in_pairs(&self.yaw) }
    }
}

/// `n` views on a turntable, (pitch, yaw) in radians: the pitch held, the yaw from `yaw0` in
/// equal steps over a full turn.
pub fn turntable(pitch: f64, yaw0: f64, n: usize) -> Vec<(f64, f64)> {
    (0..n).map(|k| (pitch, yaw0 + std::f64::consts::TAU * k as f64 / n as f64)).collect()
}

/// The release's elliptical camera path over `n` views, (pitch, yaw) in radians:
/// θ = h_mean + h_std·cos a, v = v_mean + v_std·sin a over a = linspace(0, 2π, n), with v
/// converted by arccos(1 − 2v/π) for spherical-uniform cameras, as the release does.
pub fn release_ellipse(cam: &CameraConfig, n: usize) -> Vec<(f64, f64)> {
    let steps = n.max(2);
    (0..n)
        .map(|k| {
            let t = std::f64::consts::TAU * k as f64 / (steps - 1) as f64;
            let v = cam.v_mean + cam.v_std * t.sin();
            let pitch = match cam.distribution {
                PoseDistribution::SphericalUniform => (1.0 - 2.0 * v / PI).clamp(-1.0, 1.0).acos(),
                _ => v,
            };
            (pitch, cam.h_mean + cam.h_std * t.cos())
        })
        .collect()
}

/// Row 2k of `t` repeated at row 2k + 1 (a last unpaired row stays): pairs of images that
/// differ only by their codes. Each row is still a draw from its distribution.
pub fn rows_in_pairs(t: &Tensor) -> Tensor {
    let idx: Vec<i64> = (0..t.size()[0]).map(|i| i & !1).collect();
    t.index_select(0, &Tensor::from_slice(&idx).to_device(t.device()))
}

/// Camera centres on the sphere of `radius`: `(B, 3)` = r·(sin φ cos θ, cos φ, sin φ sin θ).
pub fn camera_origins(poses: &Poses, radius: f64) -> Tensor {
    let (p, y) = (&poses.pitch, &poses.yaw);
    Tensor::cat(&[p.sin() * y.cos(), p.cos(), p.sin() * y.sin()], 1) * radius
}

/// Camera-to-world rotations `(B, 3, 3)` with columns (right, up, back) = (−left, up, −forward).
///
/// The release builds left = normalize(up₀ × forward), which is 0/0 at the poles. For a
/// camera on the sphere that cross product is sin φ·(−sin θ, 0, cos θ), so we use that
/// direction exactly (sign of sin φ, +1 at the poles, i.e. the limit from inside):
/// identical away from the poles, finite and continuous at them.
pub fn cam2world_rotation(poses: &Poses) -> Tensor {
    let origin = camera_origins(poses, 1.0);
    let forward = normalize(&(-&origin));
    let sign = poses.pitch.sin().sign().where_self(&poses.pitch.sin().ne(0.0), &poses.pitch.ones_like());
    let left = Tensor::cat(&[-poses.yaw.sin(), poses.yaw.zeros_like(), poses.yaw.cos()], 1) * sign;
    let up = normalize(&forward.linalg_cross(&left, -1));
    Tensor::stack(&[-left, up, -forward], 2)
}

/// Cam-to-world matrices `(B, 4, 4)` of `poses`, the camera at `radius` from the origin.
pub fn cam2world(poses: &Poses, radius: f64) -> Tensor {
    let b = poses.len();
    let top = Tensor::cat(&[cam2world_rotation(poses), camera_origins(poses, radius).unsqueeze(2)], 2);
    let bottom = Tensor::from_slice(&[0.0, 0.0, 0.0, 1.0]).to_kind(top.kind()).to_device(top.device());
    Tensor::cat(&[top, bottom.view([1, 1, 4]).expand([b, 1, 4], false)], 1)
}

/// Unit vectors along the last axis; a zero vector stays zero (no 0/0).
pub fn normalize(v: &Tensor) -> Tensor {
    v / v.square().sum_dim_intlist(-1, true, v.kind()).sqrt().clamp_min(1e-12)
}

/// Camera-space unit ray directions for a `res × res` image: `(res·res, 3)`, row-major
/// (index = row·res + col). Pixel centres span x ∈ [−1, 1] left→right and y ∈ [1, −1]
/// top→bottom, so the edge pixel centres lie on the field-of-view boundary.
pub fn pixel_directions(res: i64, fov_deg: f64, kind: Kind, device: Device) -> Tensor {
    let t = (fov_deg.to_radians() / 2.0).tan();
    let xs = Tensor::linspace(-1.0, 1.0, res, (kind, device));
    let ys = Tensor::linspace(1.0, -1.0, res, (kind, device));
    let x = xs.view([1, res]).expand([res, res], false).reshape([-1]);
    let y = ys.view([res, 1]).expand([res, res], false).reshape([-1]);
    // (x, y, −1/t) scaled by t: the same direction, and finite as t → 0.
    let d = Tensor::stack(&[x * t, y * t, Tensor::full([res * res], -1.0, (kind, device))], 1);
    normalize(&d)
}

/// Pinhole intrinsics in pixels: focal lengths and principal point, with pixel centres at
/// (u + ½, v + ½), x right, y down in the image (the usual photo convention); the camera
/// looks along its −z axis (OpenGL), as the poses' cam-to-world matrices do.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: i64,
    pub height: i64,
}

impl Intrinsics {
    /// The intrinsics of [`pixel_directions`]: a square `res` image whose edge pixel
    /// *centres* lie on the field-of-view boundary (the release's convention).
    pub fn from_fov(res: i64, fov_deg: f64) -> Self {
        let f = (res - 1).max(1) as f64 / (2.0 * (fov_deg.to_radians() / 2.0).tan());
        Self { fx: f, fy: f, cx: res as f64 / 2.0, cy: res as f64 / 2.0, width: res, height: res }
    }

    /// Checks that the focal lengths are positive and finite, the size positive and the
    /// principal point finite.
    pub fn validate(&self) -> crate::Result<()> {
        let focal = self.fx > 0.0 && self.fy > 0.0 && self.fx.is_finite() && self.fy.is_finite();
        let centre = self.cx.is_finite() && self.cy.is_finite();
        if !(focal && centre && self.width >= 1 && self.height >= 1) {
            return Err(crate::Error::Invalid(format!(
                "camera intrinsics {self:?}: expected positive finite focal lengths, a finite principal point and a positive size"
            )));
        }
        Ok(())
    }

    /// Camera-space unit directions `(H·W, 3)`, row-major.
    pub fn directions(&self, kind: Kind, device: Device) -> Tensor {
        let (w, h) = (self.width, self.height);
        let u = Tensor::arange(w, (kind, device)) + 0.5;
        let v = Tensor::arange(h, (kind, device)) + 0.5;
        let x = ((u - self.cx) / self.fx).view([1, w]).expand([h, w], false).reshape([-1]);
        let y = (-(v - self.cy) / self.fy).view([h, 1]).expand([h, w], false).reshape([-1]);
        normalize(&Tensor::stack(&[x, y, Tensor::full([h * w], -1.0, (kind, device))], 1))
    }
}

/// World-space rays: origins and unit directions, both `(B, R, 3)`, and optionally each
/// ray's own sampling interval.
#[derive(Debug)]
pub struct Rays {
    pub origins: Tensor,
    pub dirs: Tensor,
    /// `(B, R, 2)` [near, far] of each ray's samples; `None`: the camera's ray range.
    /// Rays with bounds also end on one sample at the camera's far end (see the renderer).
    pub bounds: Option<Tensor>,
    /// `(B, R, M)`: 1 where bin j of M equal bins of the camera's ray range may hold
    /// density, 0 where it is empty (an occupancy grid's promise). Samples are placed in
    /// occupied bins only, and empty bins count as empty space when integrating (see
    /// [`crate::render::sampler::OccupiedLength`]). Such rays also end on one sample at
    /// the camera's far end.
    pub occupied: Option<Tensor>,
}

impl Rays {
    /// Rays of `res × res` images seen from `poses` on the unit sphere.
    pub fn from_poses(poses: &Poses, res: i64, fov_deg: f64) -> Self {
        let (kind, device) = (poses.pitch.kind(), poses.pitch.device());
        let dirs_cam = pixel_directions(res, fov_deg, kind, device);
        Self::from_rotation(&cam2world_rotation(poses), &camera_origins(poses, 1.0), &dirs_cam)
    }

    /// Rays from rotations `(B, 3, 3)`, centres `(B, 3)` and camera-space directions `(R, 3)`
    /// shared by every image, or `(B, R, 3)`, each image its own (scaled patches).
    pub fn from_rotation(rot: &Tensor, origin: &Tensor, dirs_cam: &Tensor) -> Self {
        let r = dirs_cam.size()[dirs_cam.dim() - 2];
        let dirs = dirs_cam.matmul(&rot.transpose(1, 2)); // (B, R, 3)
        let origins = origin.unsqueeze(1).expand([-1, r, 3], false);
        Self { origins, dirs, bounds: None, occupied: None }
    }

    /// Rays from camera-to-world matrices `(B, 4, 4)` (user-given cameras).
    pub fn from_cam2world(c2w: &Tensor, dirs_cam: &Tensor) -> Self {
        let rot = c2w.narrow(1, 0, 3).narrow(2, 0, 3);
        let origin = c2w.narrow(1, 0, 3).select(2, 3);
        Self::from_rotation(&rot, &origin, dirs_cam)
    }

    /// The rays of real cameras: pinhole `intrinsics` and cam-to-world matrices `(B, 4, 4)`
    /// (OpenGL axes: x right, y up, looking along −z). Errors name a bad matrix shape or
    /// non-finite entries.
    pub fn from_camera(intrinsics: &Intrinsics, c2w: &Tensor) -> crate::Result<Self> {
        intrinsics.validate()?;
        if c2w.dim() != 3 || c2w.size()[1..] != [4, 4] {
            return Err(crate::Error::Shape(format!(
                "cam-to-world matrices have shape {:?}, expected [B, 4, 4]",
                c2w.size()
            )));
        }
        if !bool::try_from(c2w.isfinite().all()).unwrap_or(false) {
            return Err(crate::Error::Invalid("cam-to-world matrices have non-finite entries".into()));
        }
        Ok(Self::from_cam2world(c2w, &intrinsics.directions(c2w.kind(), c2w.device())))
    }

    /// The same rays sampled in `bounds: (B, R, 2)` = [near, far] each.
    pub fn with_bounds(self, bounds: Tensor) -> Self {
        Self { bounds: Some(bounds), ..self }
    }

    /// The same rays sampled only in their occupied bins `occupied: (B, R, M)`.
    pub fn with_occupied(self, occupied: Tensor) -> Self {
        Self { occupied: Some(occupied), ..self }
    }

    /// Rays `[start, start+len)` of every image.
    pub fn narrow(&self, start: i64, len: i64) -> Self {
        Self {
            origins: self.origins.narrow(1, start, len),
            dirs: self.dirs.narrow(1, start, len),
            bounds: self.bounds.as_ref().map(|b| b.narrow(1, start, len)),
            occupied: self.occupied.as_ref().map(|o| o.narrow(1, start, len)),
        }
    }

    /// Images `[start, start+len)`.
    pub fn narrow_batch(&self, start: i64, len: i64) -> Self {
        Self {
            origins: self.origins.narrow(0, start, len),
            dirs: self.dirs.narrow(0, start, len),
            bounds: self.bounds.as_ref().map(|b| b.narrow(0, start, len)),
            occupied: self.occupied.as_ref().map(|o| o.narrow(0, start, len)),
        }
    }

    /// The rays `idx: (K,)` of a single image (B = 1), in that order.
    pub fn select_rays(&self, idx: &Tensor) -> Self {
        Self {
            origins: self.origins.index_select(1, idx),
            dirs: self.dirs.index_select(1, idx),
            bounds: self.bounds.as_ref().map(|b| b.index_select(1, idx)),
            occupied: self.occupied.as_ref().map(|o| o.index_select(1, idx)),
        }
    }

    pub fn num_rays(&self) -> i64 {
        self.dirs.size()[1]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn max_abs(t: &Tensor) -> f64 {
        f64::try_from(t.abs().max()).unwrap()
    }

    #[test]
    fn camera_paths() {
        let t = turntable(0.5, 0.25, 4);
        let want = [0.25, 0.25 + PI / 2.0, 0.25 + PI, 0.25 + 1.5 * PI];
        assert_eq!(t.len(), 4);
        for ((p, y), w) in t.iter().zip(want) {
            assert_eq!(*p, 0.5);
            assert!((y - w).abs() < 1e-15, "{y} vs {w}");
        }
        // The release's ellipse: at a = 0 the mean pitch (converted for spherical-uniform
        // cameras) and yaw h_mean + h_std; at a = π/2 (n = 5) pitch v_mean + v_std, yaw h_mean.
        let cam = CameraConfig { distribution: PoseDistribution::SphericalUniform, ..CameraConfig::chair() };
        let e = release_ellipse(&cam, 5);
        let pitch = |v: f64| (1.0 - 2.0 * v / PI).acos();
        assert!((e[0].0 - pitch(cam.v_mean)).abs() < 1e-12 && (e[0].1 - (cam.h_mean + cam.h_std)).abs() < 1e-12);
        assert!((e[1].0 - pitch(cam.v_mean + cam.v_std)).abs() < 1e-12 && (e[1].1 - cam.h_mean).abs() < 1e-12);
        assert_eq!(e[0], e[4], "a closed path");
    }

    #[test]
    fn poses_in_pairs_repeat_the_even_ones() {
        let p = Poses::from_angles(
            &[(0.1, 1.0), (0.2, 2.0), (0.3, 3.0), (0.4, 4.0), (0.5, 5.0)],
            Kind::Double,
            Device::Cpu,
        );
        let q = p.in_pairs();
        assert_eq!(Vec::<f64>::try_from(q.pitch.view([-1])).unwrap(), [0.1, 0.1, 0.3, 0.3, 0.5]);
        assert_eq!(Vec::<f64>::try_from(q.yaw.view([-1])).unwrap(), [1.0, 1.0, 3.0, 3.0, 5.0]);
    }

    #[test]
    fn a_real_camera_gives_the_rays_of_the_equivalent_pose() {
        let poses = Poses::from_angles(&[(1.1, 0.3), (0.4, -2.0), (PI / 2.0, PI)], Kind::Double, Device::Cpu);
        let c2w = cam2world(&poses, 1.0);
        for (res, fov) in [(2, 30.0), (5, 50.0), (16, 12.0)] {
            let a = Rays::from_poses(&poses, res, fov);
            let b = Rays::from_camera(&Intrinsics::from_fov(res, fov), &c2w).unwrap();
            assert!(
                max_abs(&(&a.dirs - &b.dirs)) < 1e-12 && max_abs(&(&a.origins - &b.origins)) < 1e-12,
                "{res} {fov}"
            );
        }
        let k = Intrinsics::from_fov(4, 30.0);
        assert!(Rays::from_camera(&k, &Tensor::zeros([2, 3, 4], (Kind::Double, Device::Cpu))).is_err());
        assert!(Rays::from_camera(&Intrinsics { fx: 0.0, ..k }, &c2w).is_err());
        assert!(Rays::from_camera(&k, &(c2w * f64::NAN)).is_err());
    }

    #[test]
    fn centre_ray_points_at_the_origin() {
        let poses = Poses::from_angles(&[(1.0, 0.3), (0.5, -2.0)], Kind::Double, Device::Cpu);
        let rays = Rays::from_poses(&poses, 5, 50.0);
        let centre = rays.dirs.select(1, 12); // row 2, col 2
        let want = -camera_origins(&poses, 1.0);
        assert!(max_abs(&(centre - want)) < 1e-12);
    }

    #[test]
    fn rotation_is_orthonormal_and_right_handed_everywhere() {
        let angles: Vec<(f64, f64)> = [0.0, 1e-9, 0.3, PI / 2.0, PI - 1e-9, PI]
            .iter()
            .flat_map(|&p| [-PI, -1.0, 0.0, 2.5, PI].map(move |y| (p, y)))
            .collect();
        let poses = Poses::from_angles(&angles, Kind::Double, Device::Cpu);
        let r = cam2world_rotation(&poses);
        let eye = Tensor::eye(3, (Kind::Double, Device::Cpu));
        assert!(max_abs(&(r.transpose(1, 2).matmul(&r) - eye)) < 1e-12);
        assert!(max_abs(&(Tensor::linalg_det(&r) - 1.0)) < 1e-12);
        // Continuity at the poles: the pose at φ = 0 equals the pose at φ = 1e-9.
        let rr = r.view([6, 5, 3, 3]);
        assert!(max_abs(&(rr.get(0) - rr.get(1))) < 1e-8);
        assert!(max_abs(&(rr.get(5) - rr.get(4))) < 1e-8);
    }

    #[test]
    fn tiny_and_wide_fields_of_view_stay_finite() {
        for fov in [1e-6, 1.0, 179.999] {
            let d = pixel_directions(4, fov, Kind::Float, Device::Cpu);
            assert!(bool::try_from(d.isfinite().all()).unwrap(), "fov {fov}");
            let n = d.square().sum_dim_intlist(-1, false, Kind::Float).sqrt();
            assert!(max_abs(&(n - 1.0)) < 1e-6);
        }
    }

    #[test]
    fn sampled_pitch_stays_inside_the_range() {
        tch::manual_seed(0);
        let cam = CameraConfig::chair();
        let p = Poses::sample(&cam, 1000, Kind::Float, Device::Cpu);
        let (lo, hi) = (f64::try_from(p.pitch.min()).unwrap(), f64::try_from(p.pitch.max()).unwrap());
        assert!(lo >= cam.v_mean - cam.v_std - 1e-6 && hi <= cam.v_mean + cam.v_std + 1e-6);
        let carla = CameraConfig::carla();
        let p = Poses::sample(&carla, 1000, Kind::Float, Device::Cpu);
        let hi = f64::try_from(p.pitch.max()).unwrap();
        assert!(hi < PI / 2.0 && hi > 1.4, "{hi}");
    }
}
