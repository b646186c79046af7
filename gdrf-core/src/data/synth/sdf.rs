//! Signed distance functions of the primitives objects are built from, and the few
//! vector operations they need (f32; every distance here is exact, so sphere tracing
//! never overshoots a surface).
use std::ops::{Add, Mul, Neg, Sub};

#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct V3 {
    pub x: f32,
    pub y: f32,
    pub z: f32,
}

pub const fn v3(x: f32, y: f32, z: f32) -> V3 {
    V3 { x, y, z }
}

impl V3 {
    pub fn dot(self, o: V3) -> f32 {
        self.x * o.x + self.y * o.y + self.z * o.z
    }
    pub fn cross(self, o: V3) -> V3 {
        v3(self.y * o.z - self.z * o.y, self.z * o.x - self.x * o.z, self.x * o.y - self.y * o.x)
    }
    pub fn length(self) -> f32 {
        self.dot(self).sqrt()
    }
    pub fn normalized(self) -> V3 {
        self * (1.0 / self.length().max(1e-20))
    }
    pub fn abs(self) -> V3 {
        v3(self.x.abs(), self.y.abs(), self.z.abs())
    }
    pub fn max0(self) -> V3 {
        v3(self.x.max(0.0), self.y.max(0.0), self.z.max(0.0))
    }
    pub fn max_elem(self) -> f32 {
        self.x.max(self.y).max(self.z)
    }
    pub fn get(self, axis: usize) -> f32 {
        match axis {
            0 => self.x,
            1 => self.y,
            _ => self.z,
        }
    }
}

impl Add for V3 {
    type Output = V3;
    fn add(self, o: V3) -> V3 {
        v3(self.x + o.x, self.y + o.y, self.z + o.z)
    }
}
impl Sub for V3 {
    type Output = V3;
    fn sub(self, o: V3) -> V3 {
        v3(self.x - o.x, self.y - o.y, self.z - o.z)
    }
}
impl Mul<f32> for V3 {
    type Output = V3;
    fn mul(self, s: f32) -> V3 {
        v3(self.x * s, self.y * s, self.z * s)
    }
}
impl Neg for V3 {
    type Output = V3;
    fn neg(self) -> V3 {
        v3(-self.x, -self.y, -self.z)
    }
}

/// A rotation stored as its rows (world → local: `local = R · world`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rot {
    pub rows: [V3; 3],
}

impl Rot {
    pub const IDENTITY: Rot = Rot { rows: [v3(1.0, 0.0, 0.0), v3(0.0, 1.0, 0.0), v3(0.0, 0.0, 1.0)] };

    /// World → local for a frame whose local x, y, z axes are the given orthonormal world vectors.
    pub fn from_axes(x: V3, y: V3, z: V3) -> Rot {
        Rot { rows: [x, y, z] }
    }
    /// The frame rotated by `a` radians about the world x axis (local y tilts towards −z for a > 0).
    pub fn about_x(a: f32) -> Rot {
        let (s, c) = a.sin_cos();
        Rot::from_axes(v3(1.0, 0.0, 0.0), v3(0.0, c, -s), v3(0.0, s, c))
    }
    /// The frame rotated by `a` radians about the world y axis (local x turns towards −z for a > 0).
    pub fn about_y(a: f32) -> Rot {
        let (s, c) = a.sin_cos();
        Rot::from_axes(v3(c, 0.0, -s), v3(0.0, 1.0, 0.0), v3(s, 0.0, c))
    }
    /// A frame whose local y axis is `dir` (any unit vector); x and z are completed stably.
    pub fn y_along(dir: V3) -> Rot {
        let y = dir.normalized();
        let helper = if y.x.abs() < 0.9 { v3(1.0, 0.0, 0.0) } else { v3(0.0, 0.0, 1.0) };
        let z = helper.cross(y).normalized();
        let x = y.cross(z);
        Rot::from_axes(x, y, z)
    }
    pub fn apply(&self, p: V3) -> V3 {
        v3(self.rows[0].dot(p), self.rows[1].dot(p), self.rows[2].dot(p))
    }
    /// Local → world.
    pub fn apply_inv(&self, p: V3) -> V3 {
        self.rows[0] * p.x + self.rows[1] * p.y + self.rows[2] * p.z
    }
    /// The rotation of applying `self` in the frame `outer`: a frame given in `outer`'s
    /// local coordinates, expressed in world coordinates.
    pub fn within(&self, outer: &Rot) -> Rot {
        Rot { rows: self.rows.map(|r| outer.apply_inv(r)) }
    }
}

/// Shapes in their local frame (centred at the local origin).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape {
    /// Box with half extents `half`, edges rounded by `round` (≤ the smallest half extent).
    RoundBox {
        half: V3,
        round: f32,
    },
    /// Cylinder along local y: radius, half height, edges rounded by `round`.
    Cylinder {
        radius: f32,
        half_height: f32,
        round: f32,
    },
    /// Segment from (0, −half_length, 0) to (0, half_length, 0) swept by a sphere of `radius`.
    Capsule {
        half_length: f32,
        radius: f32,
    },
    Sphere {
        radius: f32,
    },
}

impl Shape {
    pub fn sdf(&self, p: V3) -> f32 {
        match *self {
            Shape::RoundBox { half, round } => {
                let q = p.abs() - half + v3(round, round, round);
                q.max0().length() + q.max_elem().min(0.0) - round
            }
            Shape::Cylinder { radius, half_height, round } => {
                let dx = (p.x * p.x + p.z * p.z).sqrt() - radius + round;
                let dy = p.y.abs() - half_height + round;
                let outside = (dx.max(0.0) * dx.max(0.0) + dy.max(0.0) * dy.max(0.0)).sqrt();
                outside + dx.max(dy).min(0.0) - round
            }
            Shape::Capsule { half_length, radius } => {
                let y = p.y.clamp(-half_length, half_length);
                v3(p.x, p.y - y, p.z).length() - radius
            }
            Shape::Sphere { radius } => p.length() - radius,
        }
    }

    /// Radius of a sphere about the local origin that contains the shape.
    pub fn bounding_radius(&self) -> f32 {
        match *self {
            Shape::RoundBox { half, .. } => half.length(),
            Shape::Cylinder { radius, half_height, .. } => (radius * radius + half_height * half_height).sqrt(),
            Shape::Capsule { half_length, radius } => half_length + radius,
            Shape::Sphere { radius } => radius,
        }
    }

    /// Half extents of a local axis-aligned box that contains the shape.
    pub fn local_half_extents(&self) -> V3 {
        match *self {
            Shape::RoundBox { half, .. } => half,
            Shape::Cylinder { radius, half_height, .. } => v3(radius, half_height, radius),
            Shape::Capsule { half_length, radius } => v3(radius, half_length + radius, radius),
            Shape::Sphere { radius } => v3(radius, radius, radius),
        }
    }

    /// The same shape scaled by `s` (distances scale with it, so it stays exact).
    pub fn scaled(&self, s: f32) -> Shape {
        match *self {
            Shape::RoundBox { half, round } => Shape::RoundBox { half: half * s, round: round * s },
            Shape::Cylinder { radius, half_height, round } => {
                Shape::Cylinder { radius: radius * s, half_height: half_height * s, round: round * s }
            }
            Shape::Capsule { half_length, radius } => {
                Shape::Capsule { half_length: half_length * s, radius: radius * s }
            }
            Shape::Sphere { radius } => Shape::Sphere { radius: radius * s },
        }
    }
}

/// A shape placed in the world, tagged with the semantic part it belongs to.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Prim {
    pub shape: Shape,
    /// World → local rotation.
    pub rot: Rot,
    /// World position of the local origin.
    pub pos: V3,
    /// Semantic part (index into the appearance's materials and the part frames).
    pub part: u8,
}

impl Prim {
    pub fn new(shape: Shape, rot: Rot, pos: V3, part: u8) -> Self {
        Self { shape, rot, pos, part }
    }

    pub fn sdf(&self, p: V3) -> f32 {
        self.shape.sdf(self.rot.apply(p - self.pos))
    }

    /// World-space axis-aligned bounds `(min, max)`.
    pub fn aabb(&self) -> (V3, V3) {
        let h = self.shape.local_half_extents();
        // |R^T| · h: the extent of the rotated box along each world axis.
        let col =
            |i: usize| -> f32 { self.rot.rows.iter().zip([h.x, h.y, h.z]).map(|(r, e)| r.get(i).abs() * e).sum() };
        let e = v3(col(0), col(1), col(2));
        (self.pos - e, self.pos + e)
    }

    /// Applies the similarity `x ↦ s·(x − c)` to the primitive.
    pub fn transformed(&self, c: V3, s: f32) -> Prim {
        Prim { shape: self.shape.scaled(s), rot: self.rot, pos: (self.pos - c) * s, part: self.part }
    }
}

/// A box primitive spanning the segment `a → b` (its local y axis), with the given half
/// width (local x) and half depth (local z). `x_hint` orients local x (projected normal to
/// the segment) for flat members; `None` lets [`Rot::y_along`] choose. The box overruns
/// both ends a little so that members meet without gaps.
pub fn beam(a: V3, b: V3, half_w: f32, half_d: f32, x_hint: Option<V3>, part: u8) -> Prim {
    let d = b - a;
    let y = d.normalized();
    let rot = match x_hint {
        Some(h) => {
            let z = h.cross(y).normalized();
            let x = y.cross(z);
            Rot::from_axes(x, y, z)
        }
        None => Rot::y_along(y),
    };
    let round = 0.3 * half_w.min(half_d);
    Prim::new(
        Shape::RoundBox { half: v3(half_w, d.length() * 0.5 + half_w.min(half_d) * 0.5, half_d), round },
        rot,
        (a + b) * 0.5,
        part,
    )
}

/// A round rod (capsule) from `a` to `b`.
pub fn rod(a: V3, b: V3, radius: f32, part: u8) -> Prim {
    let d = b - a;
    Prim::new(Shape::Capsule { half_length: d.length() * 0.5, radius }, Rot::y_along(d), (a + b) * 0.5, part)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Numerical check that a shape's SDF is 1-Lipschitz and zero on a known surface point.
    fn check_lipschitz(p: &Prim) {
        let mut s = 12345u32;
        let mut r = || {
            s = s.wrapping_mul(1664525).wrapping_add(1013904223);
            (s >> 8) as f32 / (1u32 << 24) as f32 * 2.0 - 1.0
        };
        for _ in 0..2000 {
            let a = v3(r(), r(), r()) * 0.5;
            let b = a + v3(r(), r(), r()) * 0.05;
            let (da, db) = (p.sdf(a), p.sdf(b));
            assert!((da - db).abs() <= (a - b).length() * 1.0001 + 1e-6, "{p:?}: {da} {db}");
        }
    }

    #[test]
    fn primitives_are_exact_distances() {
        let b = Prim::new(Shape::RoundBox { half: v3(0.1, 0.2, 0.05), round: 0.01 }, Rot::IDENTITY, V3::default(), 0);
        assert!((b.sdf(v3(0.3, 0.0, 0.0)) - 0.2).abs() < 1e-6);
        assert!((b.sdf(v3(0.0, 0.0, 0.0)) + 0.05).abs() < 1e-6);
        let c = Prim::new(
            Shape::Cylinder { radius: 0.1, half_height: 0.2, round: 0.0 },
            Rot::IDENTITY,
            v3(0.0, 1.0, 0.0),
            0,
        );
        assert!((c.sdf(v3(0.0, 1.5, 0.0)) - 0.3).abs() < 1e-6);
        assert!((c.sdf(v3(0.4, 1.0, 0.0)) - 0.3).abs() < 1e-6);
        let r = rod(v3(0.0, 0.0, 0.0), v3(1.0, 0.0, 0.0), 0.1, 0);
        assert!((r.sdf(v3(0.5, 0.3, 0.0)) - 0.2).abs() < 1e-6);
        assert!((r.sdf(v3(1.3, 0.0, 0.0)) - 0.2).abs() < 1e-6);
        let t = beam(v3(0.0, 0.0, 0.0), v3(0.2, 0.3, 0.1), 0.02, 0.03, None, 0);
        for p in [
            b,
            c,
            r,
            t,
            Prim::new(
                Shape::Sphere { radius: 0.2 },
                Rot::about_x(0.3).within(&Rot::about_y(1.0)),
                v3(0.1, 0.0, 0.0),
                0,
            ),
        ] {
            check_lipschitz(&p);
        }
    }

    #[test]
    fn rotations_are_orthonormal_and_aabbs_contain_the_shape() {
        let rot = Rot::about_x(0.4).within(&Rot::about_y(-1.1));
        let back = rot.apply_inv(rot.apply(v3(0.3, -0.2, 0.7)));
        assert!((back - v3(0.3, -0.2, 0.7)).length() < 1e-6);
        let p = beam(v3(0.1, 0.0, 0.0), v3(-0.1, 0.4, 0.2), 0.03, 0.02, Some(v3(1.0, 0.0, 0.0)), 0);
        let (lo, hi) = p.aabb();
        // Every point on a grid that is inside the shape lies inside its AABB.
        for i in 0..30 {
            for j in 0..30 {
                for k in 0..30 {
                    let q = v3(-0.5 + i as f32 / 29.0, -0.5 + j as f32 / 29.0, -0.5 + k as f32 / 29.0);
                    if p.sdf(q) < 0.0 {
                        assert!(q.x >= lo.x && q.y >= lo.y && q.z >= lo.z && q.x <= hi.x && q.y <= hi.y && q.z <= hi.z);
                    }
                }
            }
        }
    }
}
