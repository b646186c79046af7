//! Sphere-traced rendering of a union of exact SDF primitives: supersampled, ambient +
//! diffuse (key light with optional soft shadow, plus a camera fill light), white
//! background, straight alpha. Cameras follow `crate::camera` exactly (pitch from +y,
//! yaw, unit sphere, OpenGL axes, edge pixel centres on the fov boundary).
use super::material::{Appearance, PARTS};
use super::sdf::{v3, Prim, Rot, V3};
use crate::config::CameraConfig;
use crate::{Error, Result};

/// The part frames and primitives of an object, in its natural units (floor at y = 0,
/// front towards +z). Texture coordinates are taken in these units so that patterns do
/// not depend on how the object is later scaled to fit the camera.
#[derive(Debug, Clone)]
pub struct Geometry {
    pub prims: Vec<Prim>,
    /// World → part frame of each part: `q = rot · (p − origin)`.
    pub frames: [(Rot, V3); PARTS],
}

/// An object ready to render: primitives scaled and centred to fit the camera, and its
/// materials.
#[derive(Debug, Clone)]
pub struct Scene {
    prims: Vec<Prim>,
    /// Bounding sphere of each primitive: (centre, radius²), aligned with `prims`.
    bounds: Vec<(V3, f32)>,
    frames: [(Rot, V3); PARTS],
    /// Natural point at the world origin, and world units per natural unit.
    centre: V3,
    scale: f32,
    appearance: Appearance,
}

/// Radius (about the origin) that objects are scaled to: inside the field of view and
/// the ray range [ray_start, ray_end] of a camera on the unit sphere, with a 5% margin.
pub fn fit_radius(camera: &CameraConfig) -> f64 {
    let fov = (camera.fov_deg.to_radians() / 2.0).sin();
    let range = (1.0 - camera.ray_start).min(camera.ray_end - 1.0);
    0.95 * fov.min(range)
}

impl Scene {
    /// Centres the geometry's bounding box at the origin and scales it so that every
    /// primitive's bounds lie within `radius` of the origin.
    pub fn new(geometry: &Geometry, appearance: &Appearance, radius: f64) -> Result<Self> {
        let (centre, scale) = Self::fit(geometry, radius)?;
        Ok(Self::with_transform(geometry, appearance, centre, scale))
    }

    /// The natural point placed at the origin and the scale that [`Scene::new`] uses.
    pub fn fit(geometry: &Geometry, radius: f64) -> Result<(V3, f32)> {
        if geometry.prims.is_empty() || radius.is_nan() || radius <= 0.0 {
            return Err(Error::Invalid("a scene needs at least one primitive and a positive radius".into()));
        }
        let boxes: Vec<(V3, V3)> = geometry.prims.iter().map(Prim::aabb).collect();
        let lo = boxes
            .iter()
            .fold(v3(f32::MAX, f32::MAX, f32::MAX), |a, (l, _)| v3(a.x.min(l.x), a.y.min(l.y), a.z.min(l.z)));
        let hi = boxes
            .iter()
            .fold(v3(f32::MIN, f32::MIN, f32::MIN), |a, (_, h)| v3(a.x.max(h.x), a.y.max(h.y), a.z.max(h.z)));
        let centre = (lo + hi) * 0.5;
        // Farthest AABB corner of any primitive from the centre.
        let extent = boxes
            .iter()
            .map(|(l, h)| (((*l + *h) * 0.5 - centre).abs() + (*h - *l) * 0.5).length())
            .fold(0.0f32, f32::max);
        if !(extent.is_finite() && extent > 0.0) {
            return Err(Error::Invalid(format!("degenerate geometry (extent {extent})")));
        }
        Ok((centre, radius as f32 / extent))
    }

    /// The geometry with natural point `centre` at the origin, scaled by `scale` (e.g. to
    /// compare two shapes in a common frame).
    pub fn with_transform(geometry: &Geometry, appearance: &Appearance, centre: V3, scale: f32) -> Self {
        let prims: Vec<Prim> = geometry.prims.iter().map(|p| p.transformed(centre, scale)).collect();
        let bounds = prims.iter().map(|p| (p.pos, p.shape.bounding_radius().powi(2))).collect();
        Self { prims, bounds, frames: geometry.frames, centre, scale, appearance: appearance.clone() }
    }

    /// The world position of a natural-units point (e.g. a part's centre).
    pub fn to_world(&self, natural: V3) -> V3 {
        (natural - self.centre) * self.scale
    }

    /// World-space primitives (after centring and scaling).
    pub fn prims(&self) -> &[Prim] {
        &self.prims
    }

    /// Signed distance to the object at world point `p` and the albedo of its nearest
    /// primitive there (what the analytic radiance field is made of).
    pub fn sdf_albedo(&self, p: V3) -> (f32, [f32; 3]) {
        let (d, i) = self.prims.iter().enumerate().fold((f32::MAX, 0), |best, (i, prim)| {
            let d = prim.sdf(p);
            if d < best.0 {
                (d, i)
            } else {
                best
            }
        });
        (d, self.albedo(&self.prims[i], p))
    }

    fn albedo(&self, prim: &Prim, p: V3) -> [f32; 3] {
        let (rot, origin) = &self.frames[prim.part as usize];
        let natural = p * (1.0 / self.scale) + self.centre;
        self.appearance.materials[prim.part as usize].albedo(rot.apply(natural - *origin))
    }

    /// Indices of the primitives whose bounding spheres the ray `o + t·d` (t > 0) meets,
    /// with the overall entry and exit distances.
    fn candidates(&self, o: V3, d: V3, out: &mut Vec<u16>) -> (f32, f32) {
        out.clear();
        let (mut t0, mut t1) = (f32::MAX, 0.0f32);
        for (i, (c, r2)) in self.bounds.iter().enumerate() {
            let oc = o - *c;
            let b = oc.dot(d);
            let disc = b * b - (oc.dot(oc) - r2);
            if disc <= 0.0 {
                continue;
            }
            let s = disc.sqrt();
            let exit = -b + s;
            if exit <= 0.0 {
                continue;
            }
            out.push(i as u16);
            t0 = t0.min(-b - s);
            t1 = t1.max(exit);
        }
        (t0.max(0.0), t1)
    }

    /// Distance to the nearest candidate and its index.
    fn nearest(&self, p: V3, cands: &[u16]) -> (f32, u16) {
        let mut best = (f32::MAX, 0u16);
        for &i in cands {
            let d = self.prims[i as usize].sdf(p);
            if d < best.0 {
                best = (d, i);
            }
        }
        best
    }

    /// First hit of the ray: (distance, primitive index).
    fn trace(&self, o: V3, d: V3, cands: &mut Vec<u16>) -> Option<(f32, u16)> {
        let (mut t, t_end) = self.candidates(o, d, cands);
        if cands.is_empty() {
            return None;
        }
        for _ in 0..MAX_STEPS {
            let (dist, i) = self.nearest(o + d * t, cands);
            if dist < HIT_EPS {
                return Some((t, i));
            }
            t += dist;
            if t > t_end {
                return None;
            }
        }
        None
    }

    /// Penumbra factor towards the key light: 1 = lit, 0 = fully shadowed.
    fn soft_shadow(&self, p: V3, l: V3, cands: &mut Vec<u16>) -> f32 {
        let (_, t_end) = self.candidates(p, l, cands);
        let mut lit = 1.0f32;
        let mut t = 4.0 * HIT_EPS.max(1e-3);
        for _ in 0..48 {
            if t > t_end || cands.is_empty() {
                break;
            }
            let (h, _) = self.nearest(p + l * t, cands);
            lit = lit.min(SHADOW_SHARPNESS * h / t);
            if lit < 0.01 {
                return 0.0;
            }
            t += h.clamp(2e-3, 0.05);
        }
        lit.clamp(0.0, 1.0)
    }

    fn normal(&self, prim: &Prim, p: V3) -> V3 {
        // Tetrahedral differences of the hit primitive alone: exact at the surface point,
        // and sharp where primitives meet.
        const H: f32 = 2e-4;
        let k = [v3(1.0, -1.0, -1.0), v3(-1.0, -1.0, 1.0), v3(-1.0, 1.0, -1.0), v3(1.0, 1.0, 1.0)];
        k.iter().fold(V3::default(), |n, k| n + *k * prim.sdf(p + *k * H)).normalized()
    }
}

const MAX_STEPS: usize = 160;
/// Surface threshold in world units (a 64² pixel is ~0.015 at the object's distance).
const HIT_EPS: f32 = 1e-4;
const SHADOW_SHARPNESS: f32 = 10.0;
const AMBIENT: f32 = 0.28;
const KEY: f32 = 0.55;
const FILL: f32 = 0.3;

/// A pinhole camera on the unit sphere at (pitch, yaw), as in `crate::camera`.
#[derive(Debug, Clone, Copy)]
pub struct Camera {
    pub origin: V3,
    pub right: V3,
    pub up: V3,
    /// The camera's +z axis in world space (it looks along −back).
    pub back: V3,
    /// tan(fov / 2).
    pub tan_half: f32,
}

impl Camera {
    pub fn new(pitch: f64, yaw: f64, fov_deg: f64) -> Self {
        let (sp, cp) = pitch.sin_cos();
        let (sy, cy) = yaw.sin_cos();
        let origin = [sp * cy, cp, sp * sy];
        // left = sign(sin φ)·(−sin θ, 0, cos θ) (crate::camera's pole-safe look-at).
        let sign = if sp < 0.0 { -1.0 } else { 1.0 };
        let left = [-sy * sign, 0.0, cy * sign];
        let f = [-origin[0], -origin[1], -origin[2]];
        let up = [f[1] * left[2] - f[2] * left[1], f[2] * left[0] - f[0] * left[2], f[0] * left[1] - f[1] * left[0]];
        let n = (up[0] * up[0] + up[1] * up[1] + up[2] * up[2]).sqrt().max(1e-12);
        let v = |a: [f64; 3], s: f64| v3((a[0] * s) as f32, (a[1] * s) as f32, (a[2] * s) as f32);
        Self {
            origin: v(origin, 1.0),
            right: v(left, -1.0),
            up: v(up, 1.0 / n),
            back: v(origin, 1.0),
            tan_half: (fov_deg.to_radians() / 2.0).tan() as f32,
        }
    }

    /// Unit world direction through normalised image coordinates (x right, y up, both
    /// in [−1, 1] between the edge pixel centres).
    pub fn dir(&self, x: f32, y: f32) -> V3 {
        (self.right * (x * self.tan_half) + self.up * (y * self.tan_half) - self.back).normalized()
    }

    /// Pixel coordinates (column, row) of a world point in a `res × res` image, or None
    /// behind the camera.
    pub fn project(&self, p: V3, res: usize) -> Option<(f32, f32)> {
        let d = p - self.origin;
        let z = -d.dot(self.back);
        if z <= 0.0 {
            return None;
        }
        let x = d.dot(self.right) / z / self.tan_half;
        let y = d.dot(self.up) / z / self.tan_half;
        let m = (res - 1) as f32 / 2.0;
        Some(((x + 1.0) * m, (1.0 - y) * m))
    }
}

/// Image size, antialiasing and lighting options.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderOptions {
    pub resolution: usize,
    /// Samples per pixel along each axis (K × K regular grid).
    pub supersample: usize,
    pub fov_deg: f64,
    pub shadows: bool,
}

/// A rendered image; row-major, row 0 at the top.
#[derive(Debug, Clone)]
pub struct Rendered {
    pub resolution: usize,
    /// `R·R·3` colour composited on white, in [0, 1].
    pub rgb: Vec<f32>,
    /// `R·R` coverage in [0, 1].
    pub alpha: Vec<f32>,
    /// `R·R·PARTS` coverage of each part (sums to alpha per pixel).
    pub parts: Vec<f32>,
}

impl Rendered {
    /// 8-bit RGBA with straight (non-premultiplied) colour; fully transparent pixels are
    /// white. Compositing it on white gives back `rgb`.
    pub fn to_rgba8(&self) -> Vec<u8> {
        let q = |x: f32| (x.clamp(0.0, 1.0) * 255.0).round() as u8;
        let mut out = Vec::with_capacity(self.alpha.len() * 4);
        for (i, &a) in self.alpha.iter().enumerate() {
            for c in 0..3 {
                // rgb = a·straight + (1 − a)·1  ⇒  straight = (rgb − 1 + a) / a.
                let s = if a > 0.0 { (self.rgb[3 * i + c] - 1.0 + a) / a } else { 1.0 };
                out.push(q(s));
            }
            out.push(q(a));
        }
        out
    }
}

/// Renders `scene` from (pitch, yaw).
pub fn render(scene: &Scene, pitch: f64, yaw: f64, opts: &RenderOptions) -> Result<Rendered> {
    let (res, k) = (opts.resolution, opts.supersample);
    if res < 2 || k == 0 || k > 16 {
        return Err(Error::Invalid(format!(
            "render: resolution {res} (expected ≥ 2) or supersample {k} (expected 1..=16) out of range"
        )));
    }
    let cam = Camera::new(pitch, yaw, opts.fov_deg);
    let light = v3(0.35, 1.0, 0.45).normalized();
    let step = 2.0 / (res - 1) as f32; // pixel spacing in normalised image coordinates
    let inv = 1.0 / (k * k) as f32;
    let mut out = Rendered {
        resolution: res,
        rgb: vec![0.0; res * res * 3],
        alpha: vec![0.0; res * res],
        parts: vec![0.0; res * res * PARTS],
    };
    let (mut cands, mut shadow_cands) = (Vec::new(), Vec::new());
    for row in 0..res {
        for col in 0..res {
            let pix = row * res + col;
            let mut colour = [0.0f32; 3];
            for sy in 0..k {
                for sx in 0..k {
                    let x = -1.0 + step * (col as f32 + (sx as f32 + 0.5) / k as f32 - 0.5);
                    let y = 1.0 - step * (row as f32 + (sy as f32 + 0.5) / k as f32 - 0.5);
                    let d = cam.dir(x, y);
                    let Some((t, i)) = scene.trace(cam.origin, d, &mut cands) else {
                        colour.iter_mut().for_each(|c| *c += 1.0);
                        continue;
                    };
                    let prim = &scene.prims[i as usize];
                    let p = cam.origin + d * t;
                    let n = scene.normal(prim, p);
                    let key = n.dot(light).max(0.0);
                    let shadow = if opts.shadows && key > 0.0 {
                        scene.soft_shadow(p + n * 2e-3, light, &mut shadow_cands)
                    } else {
                        1.0
                    };
                    let shade =
                        (AMBIENT * (0.8 + 0.2 * n.y) + KEY * key * shadow + FILL * (-n.dot(d)).max(0.0)).min(1.0);
                    let albedo = scene.albedo(prim, p);
                    for (c, a) in colour.iter_mut().zip(albedo) {
                        *c += a * shade;
                    }
                    out.alpha[pix] += inv;
                    out.parts[pix * PARTS + prim.part as usize] += inv;
                }
            }
            for (o, c) in out.rgb[pix * 3..pix * 3 + 3].iter_mut().zip(colour) {
                *o = c * inv;
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::super::sdf::Shape;
    use super::*;
    use crate::camera::{cam2world_rotation, camera_origins, Poses, Rays};
    use tch::{Device, Kind};

    #[test]
    fn camera_matches_crate_camera_rays() {
        let angles = [(1.0, 0.3), (0.5, -2.0), (1.3, 3.0), (0.8090, -3.1)];
        let res = 7;
        let poses = Poses::from_angles(&angles, Kind::Double, Device::Cpu);
        let rays = Rays::from_poses(&poses, res, 50.0);
        for (b, &(p, y)) in angles.iter().enumerate() {
            let cam = Camera::new(p, y, 50.0);
            for row in 0..res {
                for col in 0..res {
                    let x = -1.0 + 2.0 * col as f32 / (res - 1) as f32;
                    let yy = 1.0 - 2.0 * row as f32 / (res - 1) as f32;
                    let d = cam.dir(x, yy);
                    let want = Vec::<f64>::try_from(rays.dirs.get(b as i64).get(row * res + col)).unwrap();
                    let err = (d - v3(want[0] as f32, want[1] as f32, want[2] as f32)).length();
                    assert!(err < 1e-5, "pose {b} pixel ({row},{col}): {err}");
                    // Projection inverts ray generation.
                    let (c, r) = cam.project(cam.origin + d * 0.9, res as usize).unwrap();
                    assert!((c - col as f32).abs() < 1e-3 && (r - row as f32).abs() < 1e-3);
                }
            }
        }
        // Axes equal crate::camera's rotation columns.
        let r = cam2world_rotation(&poses);
        let o = camera_origins(&poses, 1.0);
        let cam = Camera::new(angles[1].0, angles[1].1, 50.0);
        let col = |j: i64| Vec::<f64>::try_from(r.get(1).select(1, j)).unwrap();
        for (axis, want) in [(cam.right, col(0)), (cam.up, col(1)), (cam.back, col(2))] {
            assert!((axis - v3(want[0] as f32, want[1] as f32, want[2] as f32)).length() < 1e-6);
        }
        let want = Vec::<f64>::try_from(o.get(1)).unwrap();
        assert!((cam.origin - v3(want[0] as f32, want[1] as f32, want[2] as f32)).length() < 1e-6);
    }

    /// A sphere placed off-centre shows up where the camera projects its centre.
    #[test]
    fn an_off_centre_sphere_lands_at_its_projection() {
        let centre = v3(0.15, 0.1, -0.05);
        let prims = vec![Prim::new(Shape::Sphere { radius: 0.04 }, Rot::IDENTITY, centre, 0)];
        let frames = [(Rot::IDENTITY, V3::default()); PARTS];
        let scene = Scene::with_transform(&Geometry { prims, frames }, &test_appearance(), V3::default(), 1.0);
        let opts = RenderOptions { resolution: 64, supersample: 2, fov_deg: 50.0, shadows: false };
        for (p, y) in [(1.0, 0.3), (0.85, 2.5), (1.3, -1.7)] {
            let img = render(&scene, p, y, &opts).unwrap();
            let (mut m, mut cx, mut cy) = (0.0, 0.0, 0.0);
            for (i, a) in img.alpha.iter().enumerate() {
                m += a;
                cx += a * (i % 64) as f32;
                cy += a * (i / 64) as f32;
            }
            let (pc, pr) = Camera::new(p, y, 50.0).project(centre, 64).unwrap();
            assert!(m > 5.0, "sphere not visible");
            assert!((cx / m - pc).abs() < 0.5 && (cy / m - pr).abs() < 0.5, "({}, {}) vs ({pc}, {pr})", cx / m, cy / m);
        }
    }

    fn test_appearance() -> Appearance {
        let mut rng = super::super::rng::Rng::new(1, super::super::rng::Stream::Appearance);
        Appearance::sample(&mut rng)
    }

    #[test]
    fn straight_alpha_composites_back_to_the_rendered_colour() {
        let prims = vec![Prim::new(
            Shape::RoundBox { half: v3(0.2, 0.1, 0.15), round: 0.02 },
            Rot::about_y(0.4),
            V3::default(),
            2,
        )];
        let frames = [(Rot::IDENTITY, V3::default()); PARTS];
        let scene = Scene::new(&Geometry { prims, frames }, &test_appearance(), 0.38).unwrap();
        let opts = RenderOptions { resolution: 32, supersample: 3, fov_deg: 50.0, shadows: true };
        let img = render(&scene, 1.0, 0.7, &opts).unwrap();
        let rgba = img.to_rgba8();
        let mut partial = 0;
        for i in 0..32 * 32 {
            let a = rgba[4 * i + 3] as f32 / 255.0;
            if a > 0.0 && a < 1.0 {
                partial += 1;
            }
            for c in 0..3 {
                let back = rgba[4 * i + c] as f32 / 255.0 * a + (1.0 - a);
                assert!((back - img.rgb[3 * i + c]).abs() < 3.0 / 255.0);
            }
            assert!((img.parts[i * PARTS + 2] - img.alpha[i]).abs() < 1e-6);
        }
        assert!(partial > 10, "antialiased edges expected, got {partial} partial pixels");
    }
}
