//! Appearance: one material per semantic part, a colour pair and a procedural pattern
//! evaluated in the part's own coordinates (so textures follow parts when the shape
//! changes). Appearance is drawn from its own random stream, never from the shape's.
use super::rng::Rng;
use super::sdf::{v3, V3};
use serde::{Deserialize, Serialize};

/// Number of material slots; each category names its parts (see `Category::part_names`).
pub const PARTS: usize = 4;

/// Per-part materials, indexed by the part id carried by each primitive.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Appearance {
    pub materials: [Material; PARTS],
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Material {
    /// Main colour, sRGB in [0, 1].
    pub base: [f32; 3],
    /// Second colour of the pattern, sRGB in [0, 1].
    pub accent: [f32; 3],
    pub pattern: Pattern,
}

/// A procedural pattern in part coordinates (units: the object's natural scale, about 1
/// = a chair's height; see the dataset documentation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Pattern {
    Plain,
    /// Bands of `accent` covering a `duty` fraction of each `period` along `normal`.
    Stripes {
        normal: [f32; 3],
        period: f32,
        duty: f32,
        phase: f32,
    },
    /// A 3D checkerboard with cells of size `period`, shifted by `offset`.
    Checker {
        period: f32,
        offset: [f32; 3],
    },
    /// Wood-like growth rings around a line along `axis` through `centre`, warped by
    /// value noise of amplitude `warp` (in ring periods).
    Grain {
        axis: [f32; 3],
        centre: [f32; 3],
        period: f32,
        warp: f32,
        noise_seed: u32,
    },
}

impl Appearance {
    /// Draws materials from the appearance stream; about a third of the objects reuse the
    /// seat's material on the back and the legs' on the arms, as real furniture does.
    pub fn sample(rng: &mut Rng) -> Self {
        let mut materials = [(); PARTS].map(|_| Material::sample(rng));
        if rng.chance(0.35) {
            materials[1] = materials[0].clone();
        }
        if rng.chance(0.35) {
            materials[3] = materials[2].clone();
        }
        Self { materials }
    }
}

impl Material {
    pub fn sample(rng: &mut Rng) -> Self {
        let h = rng.rangef(0.0, 1.0);
        let s = rng.rangef(0.1, 0.85);
        let v = rng.rangef(0.25, 0.85);
        let base = hsv(h, s, v);
        let accent = match rng.int(0, 2) {
            0 => hsv(h, s, (v * rng.rangef(0.35, 0.65)).clamp(0.05, 1.0)), // darker
            1 => hsv(h + rng.rangef(-0.08, 0.08), s * 0.5, (v + rng.rangef(0.2, 0.4)).min(0.95)), // lighter
            _ => hsv(h + 0.5, rng.rangef(0.3, 0.9), rng.rangef(0.3, 0.9)), // contrasting
        };
        let pattern = match rng.weighted(&[1.0, 1.2, 1.0, 1.2]) {
            0 => Pattern::Plain,
            1 => Pattern::Stripes {
                normal: random_unit(rng, 0.5),
                period: rng.rangef(0.06, 0.16),
                duty: rng.rangef(0.25, 0.6),
                phase: rng.rangef(0.0, 1.0),
            },
            2 => Pattern::Checker {
                period: rng.rangef(0.05, 0.12),
                offset: [rng.rangef(0.0, 1.0), rng.rangef(0.0, 1.0), rng.rangef(0.0, 1.0)],
            },
            _ => Pattern::Grain {
                axis: random_unit(rng, 0.9),
                centre: [rng.rangef(-0.3, 0.3), rng.rangef(-0.3, 0.3), rng.rangef(-0.3, 0.3)],
                period: rng.rangef(0.03, 0.08),
                warp: rng.rangef(0.2, 1.2),
                noise_seed: rng.next_u64() as u32,
            },
        };
        Self { base, accent, pattern }
    }

    /// The albedo averaged over the pattern (the fraction of accent: 0 plain, `duty` for
    /// stripes, ½ for the checker, ¼ for grain, whose dark band is ring³): the colour a
    /// part shows from afar, what the evaluation's probe learns to read.
    pub fn mean_albedo(&self) -> [f32; 3] {
        let t = match &self.pattern {
            Pattern::Plain => 0.0,
            Pattern::Stripes { duty, .. } => *duty,
            Pattern::Checker { .. } => 0.5,
            Pattern::Grain { .. } => 0.25,
        };
        [0, 1, 2].map(|i| self.base[i] * (1.0 - t) + self.accent[i] * t)
    }

    /// Albedo at part-space point `q`.
    pub fn albedo(&self, q: V3) -> [f32; 3] {
        let t = match &self.pattern {
            Pattern::Plain => 0.0,
            Pattern::Stripes { normal, period, duty, phase } => {
                let u = q.dot(arr(*normal)) / period + phase;
                if u - u.floor() < *duty {
                    1.0
                } else {
                    0.0
                }
            }
            Pattern::Checker { period, offset } => {
                let c = |x: f32, o: f32| (x / period + o).floor() as i64;
                ((c(q.x, offset[0]) + c(q.y, offset[1]) + c(q.z, offset[2])) & 1) as f32
            }
            Pattern::Grain { axis, centre, period, warp, noise_seed } => {
                let a = arr(*axis);
                let d = q - arr(*centre);
                let radial = (d - a * d.dot(a)).length();
                let n = value_noise(q * (1.0 / (4.0 * period)), *noise_seed);
                let u = radial / period + warp * n;
                let ring = u - u.floor();
                // Late wood: a sharp dark band at the end of each ring.
                (ring * ring * ring).min(1.0)
            }
        };
        let mut out = [0.0; 3];
        for (i, o) in out.iter_mut().enumerate() {
            *o = self.base[i] + (self.accent[i] - self.base[i]) * t;
        }
        out
    }
}

fn arr(a: [f32; 3]) -> V3 {
    v3(a[0], a[1], a[2])
}

/// A unit vector; with probability `p_axis` one of the coordinate axes (upholstery-like
/// stripes), otherwise a random direction (diagonal patterns).
fn random_unit(rng: &mut Rng, p_axis: f64) -> [f32; 3] {
    if rng.chance(p_axis) {
        let mut a = [0.0; 3];
        a[rng.int(0, 2) as usize] = 1.0;
        return a;
    }
    loop {
        let v = v3(rng.rangef(-1.0, 1.0), rng.rangef(-1.0, 1.0), rng.rangef(-1.0, 1.0));
        let l = v.length();
        if l > 0.1 && l <= 1.0 {
            let u = v * (1.0 / l);
            return [u.x, u.y, u.z];
        }
    }
}

/// HSV (hue in turns, wrapping) → sRGB in [0, 1].
pub(crate) fn hsv(h: f32, s: f32, v: f32) -> [f32; 3] {
    let h = (h - h.floor()) * 6.0;
    let s = s.clamp(0.0, 1.0);
    let c = v * s;
    let x = c * (1.0 - ((h % 2.0) - 1.0).abs());
    let (r, g, b) = match h as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = v - c;
    [r + m, g + m, b + m]
}

/// Trilinearly interpolated lattice noise in [−1, 1] with smooth fade.
fn value_noise(p: V3, seed: u32) -> f32 {
    let (fx, fy, fz) = (p.x.floor(), p.y.floor(), p.z.floor());
    let (ix, iy, iz) = (fx as i32, fy as i32, fz as i32);
    let fade = |t: f32| t * t * (3.0 - 2.0 * t);
    let (tx, ty, tz) = (fade(p.x - fx), fade(p.y - fy), fade(p.z - fz));
    let h = |x: i32, y: i32, z: i32| -> f32 {
        let mut k = (x as u32).wrapping_mul(0x8da6_b343)
            ^ (y as u32).wrapping_mul(0xd816_3841)
            ^ (z as u32).wrapping_mul(0xcb1a_b31f)
            ^ seed;
        k ^= k >> 15;
        k = k.wrapping_mul(0x2c1b_3c6d);
        k ^= k >> 12;
        k = k.wrapping_mul(0x297a_2d39);
        k ^= k >> 15;
        (k >> 8) as f32 / (1u32 << 23) as f32 - 1.0
    };
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let x00 = lerp(h(ix, iy, iz), h(ix + 1, iy, iz), tx);
    let x10 = lerp(h(ix, iy + 1, iz), h(ix + 1, iy + 1, iz), tx);
    let x01 = lerp(h(ix, iy, iz + 1), h(ix + 1, iy, iz + 1), tx);
    let x11 = lerp(h(ix, iy + 1, iz + 1), h(ix + 1, iy + 1, iz + 1), tx);
    lerp(lerp(x00, x10, ty), lerp(x01, x11, ty), tz)
}

#[cfg(test)]
mod tests {
    use super::super::rng::Stream;
    use super::*;

    #[test]
    fn colours_stay_in_gamut_and_patterns_vary_over_space() {
        let mut rng = Rng::new(11, Stream::Appearance);
        let mut varied = 0;
        for _ in 0..200 {
            let m = Material::sample(&mut rng);
            let mut seen = Vec::new();
            for i in 0..50 {
                let q = v3(i as f32 * 0.013, i as f32 * 0.007, -(i as f32) * 0.011);
                let a = m.albedo(q);
                assert!(a.iter().all(|c| (0.0..=1.0).contains(c)), "{m:?} → {a:?}");
                seen.push(a);
            }
            if !matches!(m.pattern, Pattern::Plain) && seen.iter().any(|a| a != &seen[0]) {
                varied += 1;
            }
        }
        assert!(varied > 100, "only {varied} of 200 patterned materials varied");
    }

    #[test]
    fn noise_is_bounded_and_continuous() {
        for i in 0..1000 {
            let p = v3(i as f32 * 0.037, i as f32 * 0.021 - 3.0, i as f32 * -0.05);
            let (a, b) = (value_noise(p, 5), value_noise(p + v3(1e-3, 0.0, 0.0), 5));
            assert!((-1.0..=1.0).contains(&a));
            assert!((a - b).abs() < 0.01);
        }
    }
}
