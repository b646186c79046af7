//! Tables, a second category showing that nothing in the generator is chair-specific:
//! rectangular or round tops on four legs, a pedestal, trestles or solid side panels,
//! with an optional apron and lower shelf (which closes the holes between the legs).
use super::material::PARTS;
use super::render::Geometry;
use super::rng::Rng;
use super::sdf::{beam, rod, v3, Prim, Rot, Shape, V3};
use serde::{Deserialize, Serialize};
use std::f32::consts::{FRAC_PI_4, TAU};

pub const TOP: u8 = 0;
pub const LEGS: u8 = 1;
pub const APRON: u8 = 2;
pub const SHELF: u8 = 3;
pub const PART_NAMES: [&str; PARTS] = ["top", "legs", "apron", "shelf"];

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TableParams {
    pub round_top: bool,
    /// Top extent along x (the diameter for a round top).
    pub width: f32,
    /// Top extent along z (ignored for a round top).
    pub depth: f32,
    pub height: f32,
    pub top_thickness: f32,
    /// Thickness of legs and rails.
    pub member: f32,
    pub legs: TableLegs,
    /// Rails under the top between the legs (four-legged tables only).
    pub apron: bool,
    /// A lower shelf (four legs) or a low stretcher (trestles, panels); no effect on a pedestal.
    pub shelf: bool,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum TableLegs {
    Four {
        inset: f32,
        splay: f32,
        round: bool,
    },
    /// A central column on `feet` feet (0 = a disc base).
    Pedestal {
        feet: u32,
    },
    /// An upright with a foot at each end (x = ±), joined by a stretcher when `shelf`.
    Trestle,
    /// Solid side panels at each end.
    Panels,
}

impl TableParams {
    pub fn sample(rng: &mut Rng) -> Self {
        let round_top = rng.chance(0.3);
        let width = rng.rangef(0.6, 1.4);
        let legs = match rng.weighted(&[0.4, 0.25, 0.2, 0.15]) {
            0 => TableLegs::Four { inset: rng.rangef(0.0, 0.12), splay: rng.rangef(0.0, 0.12), round: rng.chance(0.5) },
            1 => TableLegs::Pedestal { feet: [0, 3, 4][rng.int(0, 2) as usize] },
            2 => TableLegs::Trestle,
            _ => TableLegs::Panels,
        };
        Self {
            round_top,
            width,
            depth: if round_top { width } else { width * rng.rangef(0.45, 1.0) },
            height: rng.rangef(0.4, 0.8),
            top_thickness: rng.rangef(0.025, 0.07),
            member: rng.rangef(0.035, 0.07),
            legs,
            apron: rng.chance(0.5),
            shelf: rng.chance(0.35),
        }
    }

    pub fn geometry(&self) -> Geometry {
        let mut prims = Vec::new();
        let (h, t) = (self.height, self.top_thickness);
        let (hw, hd) = (self.width / 2.0, self.depth / 2.0);
        let top = if self.round_top {
            Shape::Cylinder { radius: hw, half_height: t / 2.0, round: (0.3 * t).min(0.015) }
        } else {
            Shape::RoundBox { half: v3(hw, t / 2.0, hd), round: (0.3 * t).min(0.015) }
        };
        prims.push(Prim::new(top, Rot::IDENTITY, v3(0.0, h - t / 2.0, 0.0), TOP));
        let yb = h - t;
        // Largest rectangle under a round top is at 45°.
        let (ex, ez) = if self.round_top { (hw * FRAC_PI_4.cos(), hw * FRAC_PI_4.sin()) } else { (hw, hd) };
        match self.legs {
            TableLegs::Four { inset, splay, round } => self.four_legs(&mut prims, (inset, splay, round), yb, (ex, ez)),
            TableLegs::Pedestal { feet } => self.pedestal(&mut prims, feet, yb, (ex, ez)),
            TableLegs::Trestle => self.trestle(&mut prims, yb, (ex, ez)),
            TableLegs::Panels => self.panels(&mut prims, yb, (ex, ez)),
        }
        let frames = [
            (Rot::IDENTITY, v3(0.0, h, 0.0)),
            (Rot::IDENTITY, V3::default()),
            (Rot::IDENTITY, v3(0.0, yb, 0.0)),
            (Rot::IDENTITY, V3::default()),
        ];
        Geometry { prims, frames }
    }

    /// Four legs at the corners of the rectangle (`ex`, `ez`) half wide and deep under the
    /// top, inset and splayed, with an apron and a shelf where the table has them; `yb` is
    /// the top's underside.
    fn four_legs(&self, prims: &mut Vec<Prim>, (inset, splay, round): (f32, f32, bool), yb: f32, (ex, ez): (f32, f32)) {
        let (h, m) = (self.height, self.member);
        let (x, z) = ((ex - m - inset * ex).max(m), (ez - m - inset * ez).max(m));
        let corners = [v3(-x, 0.0, -z), v3(x, 0.0, -z), v3(x, 0.0, z), v3(-x, 0.0, z)];
        let legs: Vec<(V3, V3)> = corners
            .iter()
            .map(|c| (v3(c.x, yb + m / 2.0, c.z), v3(c.x * (1.0 + splay), m / 2.0, c.z * (1.0 + splay))))
            .collect();
        for &(a, b) in &legs {
            prims.push(if round { rod(a, b, m / 2.0, LEGS) } else { beam(b, a, m / 2.0, m / 2.0, None, LEGS) });
        }
        if self.apron {
            let ah = (0.12 * h).max(m);
            for i in 0..4 {
                let (a, b) = (corners[i], corners[(i + 1) % 4]);
                let mid = (a + b) * 0.5;
                let len = (b - a).length();
                let along_x = (b - a).x.abs() > 1e-6;
                let half = if along_x { v3(len / 2.0, ah / 2.0, 0.3 * m) } else { v3(0.3 * m, ah / 2.0, len / 2.0) };
                prims.push(Prim::new(
                    Shape::RoundBox { half, round: 0.005 },
                    Rot::IDENTITY,
                    v3(mid.x, yb - ah / 2.0, mid.z),
                    APRON,
                ));
            }
        }
        if self.shelf {
            let y = 0.2 * h;
            let f = 1.0 + splay * (1.0 - y / yb);
            prims.push(Prim::new(
                Shape::RoundBox { half: v3(x * f, 0.012, z * f), round: 0.006 },
                Rot::IDENTITY,
                v3(0.0, y, 0.0),
                SHELF,
            ));
        }
    }

    /// A central column on a disc or on `feet` feet.
    fn pedestal(&self, prims: &mut Vec<Prim>, feet: u32, yb: f32, (ex, ez): (f32, f32)) {
        let m = self.member;
        let col = m.max(0.05);
        prims.push(Prim::new(
            Shape::Cylinder { radius: col, half_height: yb / 2.0, round: 0.0 },
            Rot::IDENTITY,
            v3(0.0, yb / 2.0, 0.0),
            LEGS,
        ));
        let reach = 0.7 * ex.min(ez).max(0.25);
        if feet == 0 {
            prims.push(Prim::new(
                Shape::Cylinder { radius: reach, half_height: 0.015, round: 0.01 },
                Rot::IDENTITY,
                v3(0.0, 0.015, 0.0),
                APRON,
            ));
        } else {
            for i in 0..feet {
                let (s, c) = (TAU * (i as f32 + 0.5) / feet as f32).sin_cos();
                prims.push(beam(
                    v3(0.0, 0.04, 0.0),
                    v3(reach * c, 0.02, reach * s),
                    0.025,
                    0.02,
                    Some(v3(-s, 0.0, c)),
                    APRON,
                ));
            }
        }
    }

    /// Two trestles (an upright on a foot, under a bearer) and a stretcher for a shelf.
    fn trestle(&self, prims: &mut Vec<Prim>, yb: f32, (ex, ez): (f32, f32)) {
        let m = self.member;
        let x = ex - 1.5 * m;
        for s in [-1.0, 1.0] {
            prims.push(beam(v3(s * x, 0.0, 0.0), v3(s * x, yb, 0.0), m / 2.0, 1.5 * m, None, LEGS));
            prims.push(Prim::new(
                Shape::RoundBox { half: v3(m / 2.0, m / 2.0, 0.85 * ez), round: 0.01 },
                Rot::IDENTITY,
                v3(s * x, m / 2.0, 0.0),
                APRON,
            ));
            prims.push(Prim::new(
                Shape::RoundBox { half: v3(m / 2.0, m / 2.0, 0.85 * ez), round: 0.01 },
                Rot::IDENTITY,
                v3(s * x, yb - m / 2.0, 0.0),
                APRON,
            ));
        }
        if self.shelf {
            prims.push(Prim::new(
                Shape::RoundBox { half: v3(x, m / 2.0, m / 2.0), round: 0.01 },
                Rot::IDENTITY,
                v3(0.0, 0.35 * yb, 0.0),
                SHELF,
            ));
        }
    }

    /// Two side panels and a back panel for a shelf.
    fn panels(&self, prims: &mut Vec<Prim>, yb: f32, (ex, ez): (f32, f32)) {
        let m = self.member;
        let x = ex - m;
        for s in [-1.0, 1.0] {
            prims.push(Prim::new(
                Shape::RoundBox { half: v3(m / 2.0, yb / 2.0, 0.9 * ez), round: 0.01 },
                Rot::IDENTITY,
                v3(s * x, yb / 2.0, 0.0),
                LEGS,
            ));
        }
        if self.shelf {
            prims.push(Prim::new(
                Shape::RoundBox { half: v3(x, 0.06, 0.015), round: 0.008 },
                Rot::IDENTITY,
                v3(0.0, 0.5 * yb, -0.6 * ez),
                SHELF,
            ));
        }
    }
}
