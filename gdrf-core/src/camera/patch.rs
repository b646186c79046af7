//! Scaled patches (EpiGRAF's patch training, for the scaled-patch step): a P×P
//! patch of an R×R view, of side `scale` ∈ [P/R, 1] of the image at `offset` ∈ [0, 1 − s]²,
//! both in image extents (x right, y down). Patch pixel k covers [o·R + k·w, o·R + (k+1)·w]
//! in image pixel units, w = s·R/P ≥ 1.
//!
//! The generator's rays go through the centres of those footprints; the real image is
//! averaged over them (the area filter of the dataset cache, `data::folder::area_resize`).
//! Pixel extents, not EpiGRAF's `linspace(−1, 1, P)` with aligned corners, so that at
//! s = P/R with whole-pixel offsets a patch is the image's own pixels (EpiGRAF's spacing is
//! then 2s/(P − 1), not 2/(R − 1)), and at s = 1 it is the image the cache makes at P².
//! Averaging also keeps real patches of large s free of the aliasing of bilinear sampling.
use super::{cam2world_rotation, camera_origins, normalize, Poses, Rays};
use crate::{Error, Result};
use tch::{Device, Kind, Tensor};

/// One image's patch: side and top-left corner as fractions of the image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Patch {
    pub scale: f64,
    /// (x, y) of the top-left corner, y down.
    pub offset: (f64, f64),
}

impl Patch {
    /// The whole image.
    pub fn whole() -> Self {
        Self { scale: 1.0, offset: (0.0, 0.0) }
    }

    /// `[s, ox, oy]`: what the discriminator is told of the patch
    /// ([`crate::disc::Judge::judge_patches`]).
    pub fn coords(&self) -> [f64; 3] {
        [self.scale, self.offset.0, self.offset.1]
    }

    /// Refuses a patch that is not inside the image or finer than its pixels, for a `p`-pixel
    /// patch of an `r`-pixel image.
    pub fn check(&self, p: i64, r: i64) -> Result<()> {
        let min = p as f64 / r as f64;
        let eps = 1e-9;
        let inside = |o: f64| o >= -eps && o <= 1.0 - self.scale + eps;
        // Written so that NaN fails every comparison and is refused.
        let sized = (1..=r).contains(&p) && self.scale >= min - eps && self.scale <= 1.0 + eps;
        if !(sized && inside(self.offset.0) && inside(self.offset.1)) {
            return Err(Error::Invalid(format!(
                "patch {self:?} of {p}² in a {r}² image: expected a scale in [{min}, 1] and offsets in [0, 1 − scale]"
            )));
        }
        Ok(())
    }

    /// Start (pixel units) and width of the footprints along x and y.
    fn footprints(&self, p: i64, r: i64) -> ((f64, f64), f64) {
        let r = r as f64;
        ((self.offset.0 * r, self.offset.1 * r), self.scale * r / p as f64)
    }
}

/// `t` (a 1-d table of an image's pixel-centre coordinates) at fractional pixel indices
/// `i: (P,)` in [0, len − 1], linearly: at whole indices exactly the table's entries.
fn at_index(t: &Tensor, i: &Tensor) -> Tensor {
    let n = t.size()[0];
    let lo = i.floor().clamp(0.0, (n - 1) as f64);
    let frac = i - &lo;
    let lo = lo.to_kind(Kind::Int64);
    let hi = (&lo + 1).clamp_max(n - 1);
    let (a, b) = (t.index_select(0, &lo), t.index_select(0, &hi));
    &a + frac.to_kind(a.kind()) * (&b - &a)
}

/// Fractional pixel indices `(P,)` of the footprint centres starting at `start`, `width`
/// apart (pixel centre j + ½ is index j).
fn centre_indices(start: f64, width: f64, p: i64) -> Tensor {
    (Tensor::arange(p, (Kind::Double, Device::Cpu)) + 0.5) * width + start - 0.5
}

/// Camera-space unit directions `(P·P, 3)`, row-major, through the centres of `patch`'s
/// pixels in a `r × r` view of field of view `fov_deg`: the rays of
/// [`super::pixel_directions`] at those (fractional) pixels, bit for bit at whole ones.
pub fn patch_directions(patch: &Patch, p: i64, r: i64, fov_deg: f64, kind: Kind, device: Device) -> Tensor {
    let t = (fov_deg.to_radians() / 2.0).tan();
    let ((x0, y0), w) = patch.footprints(p, r);
    let xs = at_index(&Tensor::linspace(-1.0, 1.0, r, (kind, device)), &centre_indices(x0, w, p).to_device(device));
    let ys = at_index(&Tensor::linspace(1.0, -1.0, r, (kind, device)), &centre_indices(y0, w, p).to_device(device));
    let x = xs.view([1, p]).expand([p, p], false).reshape([-1]);
    let y = ys.view([p, 1]).expand([p, p], false).reshape([-1]);
    let d = Tensor::stack(&[x * t, y * t, Tensor::full([p * p], -1.0, (kind, device))], 1);
    normalize(&d)
}

/// Rays `(B, P·P, 3)` of one patch per image of `r × r` views from `poses`.
pub fn patch_rays(poses: &Poses, patches: &[Patch], p: i64, r: i64, fov_deg: f64) -> Result<Rays> {
    if patches.len() as i64 != poses.len() {
        return Err(Error::Shape(format!("{} patches for {} poses", patches.len(), poses.len())));
    }
    for patch in patches {
        patch.check(p, r)?;
    }
    let (kind, device) = (poses.pitch.kind(), poses.pitch.device());
    let dirs: Vec<Tensor> = patches.iter().map(|q| patch_directions(q, p, r, fov_deg, kind, device)).collect();
    // (B, P², 3) by (B, 3, 3): the same rotation as the full image's (R, 3) by (B, 3, 3), in a
    // batched product whose rounding differs from it by an ulp or so.
    Ok(Rays::from_rotation(&cam2world_rotation(poses), &camera_origins(poses, 1.0), &Tensor::stack(&dirs, 0)))
}

/// `(P, R)` weights of the footprints starting at `start`, `width` apart: the share of each
/// footprint that pixel i covers (rows sum to 1).
fn footprint_weights(start: f64, width: f64, p: i64, r: i64) -> Tensor {
    let lo = Tensor::arange(p, (Kind::Double, Device::Cpu)) * width + start;
    let (lo, hi) = (lo.view([p, 1]), (&lo + width).view([p, 1]));
    let i = Tensor::arange(r, (Kind::Double, Device::Cpu)).view([1, r]);
    (hi.minimum(&(&i + 1.0)) - lo.maximum(&i)).clamp_min(0.0) / width
}

/// Real patches `(B, C, P, P)` of images `(B, C, R, R)`: each image averaged over its
/// patch's pixel footprints (the area filter). At s = 1 this is the image area-resized to
/// P², at s = P/R with whole offsets an exact crop.
pub fn real_patches(images: &Tensor, patches: &[Patch], p: i64) -> Result<Tensor> {
    let s = images.size();
    if s.len() != 4 || s[2] != s[3] || s[0] != patches.len() as i64 {
        return Err(Error::Shape(format!("images of shape {s:?} for {} square patches", patches.len())));
    }
    let r = s[2];
    let (kind, device) = (images.kind(), images.device());
    let mut rows = Vec::new();
    let mut cols = Vec::new();
    for patch in patches {
        patch.check(p, r)?;
        let ((x0, y0), w) = patch.footprints(p, r);
        rows.push(footprint_weights(y0, w, p, r));
        cols.push(footprint_weights(x0, w, p, r));
    }
    let wy = Tensor::stack(&rows, 0).to_kind(kind).to_device(device).unsqueeze(1); // (B, 1, P, R)
    let wx = Tensor::stack(&cols, 0).to_kind(kind).to_device(device).unsqueeze(1);
    Ok(wy.matmul(images).matmul(&wx.transpose(2, 3)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::pixel_directions;

    fn poses(b: usize) -> Poses {
        let angles: Vec<(f64, f64)> = (0..b).map(|i| (1.2 + 0.1 * i as f64, -0.7 + 0.9 * i as f64)).collect();
        Poses::from_angles(&angles, Kind::Float, Device::Cpu)
    }

    /// At s = P/R and whole-pixel offsets a patch's rays are the full image's rays at its
    /// pixels: bit for bit in camera space, to rounding in world space.
    #[test]
    fn native_patches_are_the_images_own_rays() {
        let (p, r, fov) = (4, 12, 12.0);
        let ps = poses(2);
        let full = Rays::from_poses(&ps, r, fov);
        let patches = [
            Patch { scale: 4.0 / 12.0, offset: (3.0 / 12.0, 5.0 / 12.0) },
            Patch { scale: 1.0 / 3.0, offset: (8.0 / 12.0, 0.0) },
        ];
        let rays = patch_rays(&ps, &patches, p, r, fov).unwrap();
        for (b, (col0, row0)) in [(3, 5), (8, 0)].into_iter().enumerate() {
            let idx: Vec<i64> = (0..p).flat_map(|y| (0..p).map(move |x| (row0 + y) * r + col0 + x)).collect();
            let idx = Tensor::from_slice(&idx);
            // Camera space: the image's own directions, bit for bit.
            let cam = patch_directions(&patches[b], p, r, fov, Kind::Float, Device::Cpu);
            assert!(cam.equal(&pixel_directions(r, fov, Kind::Float, Device::Cpu).index_select(0, &idx)));
            // World space: the same rotation, in a batched product (an ulp or so apart).
            let want = full.dirs.get(b as i64).index_select(0, &idx);
            let got = rays.dirs.get(b as i64);
            assert!(got.allclose(&want, 0.0, 5e-7, false), "image {b}: {got} vs {want}");
            assert!(rays.origins.get(b as i64).equal(&full.origins.get(b as i64).narrow(0, 0, p * p)));
        }
    }

    /// At other scales the rays go through the footprint centres: linear in the pixel index,
    /// so equal to the directions of the image's coordinates at those fractional pixels.
    #[test]
    fn scaled_patches_go_through_their_footprint_centres() {
        let (p, r, fov) = (4, 10, 30.0);
        let patch = Patch { scale: 0.7, offset: (0.1, 0.25) };
        let d = patch_directions(&patch, p, r, fov, Kind::Double, Device::Cpu);
        // Footprints of width 0.7·10/4 = 1.75 from (1, 2.5): centres at 1 + 1.75(k + ½).
        let t = (fov.to_radians() / 2.0).tan();
        for (row, col) in [(0i64, 0i64), (1, 3), (3, 2)] {
            let cx = 1.0 + 1.75 * (col as f64 + 0.5) - 0.5;
            let cy = 2.5 + 1.75 * (row as f64 + 0.5) - 0.5;
            let (x, y) = (-1.0 + 2.0 * cx / 9.0, 1.0 - 2.0 * cy / 9.0);
            let n = (x * x * t * t + y * y * t * t + 1.0).sqrt();
            let want = Tensor::from_slice(&[x * t / n, y * t / n, -1.0 / n]);
            let got = d.get(row * p + col);
            assert!(got.allclose(&want, 1e-12, 1e-12, false), "({row}, {col}): {got} vs {want}");
        }
        // The whole image at P = R is the image's own rays.
        let whole = patch_directions(&Patch::whole(), r, r, fov, Kind::Double, Device::Cpu);
        assert!(whole.equal(&pixel_directions(r, fov, Kind::Double, Device::Cpu)));
    }

    /// A scale-1 patch of a real image is the image area-resized to P² as the dataset cache
    /// does; a native patch at whole offsets is an exact crop.
    #[test]
    fn real_patches_average_over_the_footprints() {
        let (p, r) = (6, 16);
        let img = Tensor::rand([2, 3, r, r], (Kind::Float, Device::Cpu));
        let whole = real_patches(&img, &[Patch::whole(), Patch::whole()], p).unwrap();
        for b in 0..2 {
            let planes: Vec<f32> = Vec::<f32>::try_from(img.get(b).reshape([-1])).unwrap();
            let cache = crate::data::folder::area_resize(&planes, 3, r as usize, p as usize);
            let cache = Tensor::from_slice(&cache).view([3, p, p]);
            let got = whole.get(b);
            assert!(got.allclose(&cache, 1e-6, 1e-6, false), "max diff {}", (&got - &cache).abs().max());
        }
        let native = Patch { scale: 6.0 / 16.0, offset: (2.0 / 16.0, 9.0 / 16.0) };
        let crop = real_patches(&img.narrow(0, 0, 1), &[native], p).unwrap();
        assert!(crop.get(0).equal(&img.get(0).narrow(1, 9, p).narrow(2, 2, p)));
        // Out of the image, finer than its pixels, or the wrong count: errors naming the patch.
        let bad = Patch { scale: 0.2, offset: (0.0, 0.0) };
        assert!(real_patches(&img.narrow(0, 0, 1), &[bad], p).unwrap_err().to_string().contains("scale"));
        let out = Patch { scale: 0.5, offset: (0.6, 0.0) };
        assert!(real_patches(&img.narrow(0, 0, 1), &[out], p).is_err());
        let nan = Patch { scale: f64::NAN, offset: (0.0, 0.0) };
        assert!(real_patches(&img.narrow(0, 0, 1), &[nan], p).is_err());
        assert!(real_patches(&img, &[native], p).is_err());
    }
}
