//! Chairs whose topology varies: five leg structures, five back styles (holes from
//! slats, rungs or a frame; none for stools), open or solid arms, square or round seats,
//! and continuous proportions. Natural units are metres; floor at y = 0, front at +z.
use super::material::PARTS;
use super::render::Geometry;
use super::rng::Rng;
use super::sdf::{beam, rod, v3, Prim, Rot, Shape, V3};
use serde::{Deserialize, Serialize};
use std::f32::consts::{FRAC_PI_2, TAU};

pub const SEAT: u8 = 0;
pub const BACK: u8 = 1;
pub const LEGS: u8 = 2;
pub const ARMS: u8 = 3;
pub const PART_NAMES: [&str; PARTS] = ["seat", "back", "legs", "arms"];

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChairParams {
    pub seat: SeatShape,
    /// Seat extent along x (the diameter for a round seat).
    pub seat_width: f32,
    /// Seat extent along z (ignored for a round seat).
    pub seat_depth: f32,
    /// Height of the seat's top surface above the floor.
    pub seat_height: f32,
    pub seat_thickness: f32,
    /// Thickness of legs, posts, rails and tubes.
    pub member: f32,
    pub legs: Legs,
    pub back: Back,
    /// Height of the back above the seat, measured along the (tilted) back.
    pub back_height: f32,
    /// Backwards lean of the back in radians.
    pub back_tilt: f32,
    pub arms: Arms,
    /// Height of the armrests above the seat.
    pub arm_height: f32,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SeatShape {
    Square,
    Round,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Legs {
    /// Four legs, splayed outwards by `splay` (foot offset per unit height), round or
    /// square, optionally joined by a ring of stretchers (more holes).
    Four { splay: f32, round: bool, stretchers: bool },
    /// Three round legs at 120°.
    Three { splay: f32 },
    /// Office-chair base: central column, `spokes` radial arms with casters.
    Swivel { spokes: u32, radius: f32 },
    /// Tubular frame: a closed sled loop per side, or a cantilever (front upright only,
    /// runners joined at the back).
    Sled { cantilever: bool },
    /// A solid pedestal: a block, or a column on a disc of `base_radius`.
    Pedestal { block: bool, base_radius: f32 },
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Back {
    /// A stool.
    None,
    Solid,
    /// Posts, a top rail and `count` vertical slats with gaps between them.
    Slats {
        count: u32,
    },
    /// Posts and `rungs` horizontal rungs.
    Ladder {
        rungs: u32,
    },
    /// Posts, top and bottom rails of height `rail` around one opening.
    Frame {
        rail: f32,
    },
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Arms {
    None,
    /// A front post and an armrest per side: each closes a loop with seat and back.
    Open,
    /// A solid side panel per side.
    Panel,
}

impl ChairParams {
    /// Draws a chair from the shape stream.
    pub fn sample(rng: &mut Rng) -> Self {
        let seat = if rng.chance(0.3) { SeatShape::Round } else { SeatShape::Square };
        let back = match rng.weighted(&[0.15, 0.25, 0.2, 0.2, 0.2]) {
            0 => Back::None,
            1 => Back::Solid,
            2 => Back::Slats { count: rng.int(2, 6) },
            3 => Back::Ladder { rungs: rng.int(2, 4) },
            _ => Back::Frame { rail: rng.rangef(0.05, 0.09) },
        };
        let stool = back == Back::None;
        let legs = match rng.weighted(&[0.3, 0.15, 0.2, 0.15, 0.2]) {
            0 => Legs::Four { splay: rng.rangef(0.0, 0.15), round: rng.chance(0.5), stretchers: rng.chance(0.4) },
            1 => Legs::Three { splay: rng.rangef(0.05, 0.2) },
            2 => Legs::Swivel { spokes: rng.int(4, 6), radius: rng.rangef(0.26, 0.33) },
            3 => Legs::Sled { cantilever: rng.chance(0.5) },
            _ => Legs::Pedestal { block: rng.chance(0.35), base_radius: rng.rangef(0.18, 0.27) },
        };
        let arms = if stool || seat == SeatShape::Round {
            Arms::None
        } else {
            [Arms::None, Arms::Open, Arms::Panel][rng.weighted(&[0.5, 0.3, 0.2])]
        };
        let seat_width = rng.rangef(0.4, 0.56);
        Self {
            seat,
            seat_width,
            seat_depth: if seat == SeatShape::Round { seat_width } else { rng.rangef(0.38, 0.52) },
            seat_height: if stool { rng.rangef(0.45, 0.75) } else { rng.rangef(0.38, 0.52) },
            seat_thickness: rng.rangef(0.025, 0.09),
            member: rng.rangef(0.025, 0.05),
            legs,
            back,
            back_height: rng.rangef(0.3, 0.55),
            back_tilt: rng.rangef(0.0, 0.3),
            arms,
            arm_height: rng.rangef(0.16, 0.26),
        }
    }

    pub fn geometry(&self) -> Geometry {
        let mut prims = Vec::new();
        let (h, t, m) = (self.seat_height, self.seat_thickness, self.member);
        let (hw, hd) = (self.seat_width / 2.0, self.seat_depth / 2.0);
        let round = self.seat == SeatShape::Round;

        // Seat.
        let seat_centre = v3(0.0, h - t / 2.0, 0.0);
        let seat = if round {
            Shape::Cylinder { radius: hw, half_height: t / 2.0, round: (0.3 * t).min(0.015) }
        } else {
            Shape::RoundBox { half: v3(hw, t / 2.0, hd), round: (0.3 * t).min(0.02) }
        };
        prims.push(Prim::new(seat, Rot::IDENTITY, seat_centre, SEAT));

        // Back, in a frame tilted about its bottom edge.
        let (bw, zb) = if round { (0.6 * hw, -0.8 * hw + m / 2.0) } else { (hw - m / 2.0, -hd + m / 2.0) };
        let back_rot = Rot::about_x(self.back_tilt);
        let pivot = v3(0.0, h, zb);
        self.back_prims(&mut prims, back_rot, pivot, bw);

        // Legs.
        let yb = h - t; // underside of the seat
        self.leg_prims(&mut prims, yb, hw, hd);

        // Arms (square seats with a back only).
        if self.back != Back::None && !round {
            let x = hw - m / 2.0;
            let top = h + self.arm_height;
            let z_back = zb - self.arm_height * self.back_tilt.tan();
            let z_front = hd - m;
            for s in [-1.0, 1.0] {
                match self.arms {
                    Arms::None => {}
                    Arms::Open => {
                        prims.push(beam(
                            v3(s * x, h - t / 2.0, z_front),
                            v3(s * x, top, z_front),
                            m / 2.0,
                            m / 2.0,
                            None,
                            ARMS,
                        ));
                        prims.push(beam(
                            v3(s * x, top, z_front + m),
                            v3(s * x, top, z_back),
                            0.8 * m,
                            0.4 * m,
                            Some(v3(1.0, 0.0, 0.0)),
                            ARMS,
                        ));
                    }
                    Arms::Panel => {
                        let (za, zc) = (z_back.min(zb), z_front + m / 2.0);
                        prims.push(Prim::new(
                            Shape::RoundBox {
                                half: v3(0.6 * m, (self.arm_height + t) / 2.0, (zc - za) / 2.0),
                                round: 0.3 * m,
                            },
                            Rot::IDENTITY,
                            v3(s * x, h - t + (self.arm_height + t) / 2.0, (za + zc) / 2.0),
                            ARMS,
                        ));
                    }
                }
            }
        }

        let frames = [
            (Rot::IDENTITY, v3(0.0, h, 0.0)),
            (back_rot, pivot),
            (Rot::IDENTITY, V3::default()),
            (Rot::IDENTITY, v3(0.0, h, 0.0)),
        ];
        Geometry { prims, frames }
    }

    fn back_prims(&self, prims: &mut Vec<Prim>, rot: Rot, pivot: V3, bw: f32) {
        let (m, bh, t) = (self.member, self.back_height, self.seat_thickness);
        // Back-local (x, y along the back, z forward) → world.
        let at = |x: f32, y: f32| pivot + rot.apply_inv(v3(x, y, 0.0));
        let panel = |prims: &mut Vec<Prim>, x0: f32, x1: f32, y0: f32, y1: f32, depth: f32| {
            prims.push(Prim::new(
                Shape::RoundBox {
                    half: v3((x1 - x0) / 2.0, (y1 - y0) / 2.0, depth / 2.0),
                    round: 0.3 * depth.min(y1 - y0).min(x1 - x0),
                },
                rot,
                at((x0 + x1) / 2.0, (y0 + y1) / 2.0),
                BACK,
            ));
        };
        let posts = |prims: &mut Vec<Prim>, half_w: f32| {
            for s in [-1.0, 1.0] {
                prims.push(beam(
                    at(s * bw, -t / 2.0),
                    at(s * bw, bh),
                    half_w,
                    m / 2.0,
                    Some(rot.apply_inv(v3(1.0, 0.0, 0.0))),
                    BACK,
                ));
            }
        };
        let rail = (1.5 * m).max(0.04);
        match self.back {
            Back::None => {}
            Back::Solid => panel(prims, -bw - m / 2.0, bw + m / 2.0, -t / 2.0, bh, m.max(0.035)),
            Back::Slats { count } => {
                posts(prims, m / 2.0);
                panel(prims, -bw, bw, bh - rail, bh, m);
                let spacing = 2.0 * bw / (count + 1) as f32;
                for i in 1..=count {
                    let x = -bw + spacing * i as f32;
                    panel(prims, x - 0.22 * spacing, x + 0.22 * spacing, -t / 2.0, bh - rail / 2.0, 0.6 * m);
                }
            }
            Back::Ladder { rungs } => {
                posts(prims, m / 2.0);
                let lowest = 0.35 * bh;
                for i in 0..rungs {
                    let y = lowest + (bh - rail - lowest) * i as f32 / (rungs - 1).max(1) as f32;
                    panel(prims, -bw, bw, y, y + 0.7 * rail, 0.7 * m);
                }
            }
            Back::Frame { rail: r } => {
                posts(prims, r / 2.0);
                panel(prims, -bw, bw, bh - r, bh, m);
                let bottom = 0.15 * bh;
                panel(prims, -bw, bw, bottom, bottom + r, m);
            }
        }
    }

    /// The legs under a seat whose underside is at height `yb`, `hw` × `hd` half wide and deep.
    fn leg_prims(&self, prims: &mut Vec<Prim>, yb: f32, hw: f32, hd: f32) {
        let m = self.member;
        match self.legs {
            Legs::Four { splay, round, stretchers } => self.four_legs(prims, (splay, round, stretchers), yb, hw, hd),
            Legs::Three { splay } => {
                let r = 0.65 * hw.min(hd);
                for i in 0..3 {
                    let (s, c) = (FRAC_PI_2 + TAU * i as f32 / 3.0).sin_cos();
                    let (top, foot) = self.splayed(r * c, r * s, splay, yb);
                    prims.push(rod(top, foot + v3(0.0, m / 2.0, 0.0), m / 2.0, LEGS));
                }
            }
            Legs::Swivel { spokes, radius } => swivel_base(prims, spokes, radius, yb),
            Legs::Sled { cantilever } => self.sled(prims, cantilever, yb, hw, hd),
            Legs::Pedestal { block, base_radius } => self.pedestal(prims, block, base_radius, yb, hw, hd),
        }
    }

    /// The top of a leg at (`x`, `z`) under a seat at height `yb`, and its foot, splayed
    /// outwards by `splay` × `yb`.
    fn splayed(&self, x: f32, z: f32, splay: f32, yb: f32) -> (V3, V3) {
        let out = v3(x, 0.0, z).normalized() * (splay * yb);
        (v3(x, yb + self.member / 2.0, z), v3(x + out.x, 0.0, z + out.z))
    }

    /// Four corner legs, round or square, splayed, with stretchers between them if asked.
    fn four_legs(
        &self,
        prims: &mut Vec<Prim>,
        (splay, round, stretchers): (f32, bool, bool),
        yb: f32,
        hw: f32,
        hd: f32,
    ) {
        let m = self.member;
        let round_seat = self.seat == SeatShape::Round;
        let corners: Vec<(f32, f32)> = if round_seat {
            (0..4)
                .map(|i| (TAU * (i as f32 + 0.5) / 4.0).sin_cos())
                .map(|(s, c)| (0.7 * hw * c, 0.7 * hw * s))
                .collect()
        } else {
            [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
                .iter()
                .map(|(a, b)| (a * (hw - 0.75 * m), b * (hd - 0.75 * m)))
                .collect()
        };
        let legs: Vec<(V3, V3)> = corners.iter().map(|&(x, z)| self.splayed(x, z, splay, yb)).collect();
        for &(top, foot) in &legs {
            let foot = foot + v3(0.0, m / 2.0, 0.0);
            prims.push(if round {
                rod(top, foot, m / 2.0, LEGS)
            } else {
                beam(foot, top, m / 2.0, m / 2.0, None, LEGS)
            });
        }
        if stretchers {
            let f = 0.25;
            let at = |(top, foot): (V3, V3)| foot + (top - foot) * f;
            for i in 0..4 {
                prims.push(rod(at(legs[i]), at(legs[(i + 1) % 4]), 0.35 * m, LEGS));
            }
        }
    }

    /// Two runners along the sides, closed into loops or (cantilever) open at the back.
    fn sled(&self, prims: &mut Vec<Prim>, cantilever: bool, yb: f32, hw: f32, hd: f32) {
        let m = self.member;
        let round_seat = self.seat == SeatShape::Round;
        let r = 0.45 * m;
        let x = if round_seat { 0.7 * hw } else { hw - 1.5 * r };
        let zf = if round_seat { 0.7 * hw } else { hd - r };
        let top = yb - r;
        for s in [-1.0, 1.0] {
            let x = s * x;
            if cantilever {
                let (front, back) = (v3(x, r, zf + 0.05), v3(x, r, -0.7 * zf));
                prims.push(rod(back, front, r, LEGS));
                prims.push(rod(front, v3(x, top, 0.85 * zf), r, LEGS));
                prims.push(rod(v3(x, top, 0.85 * zf), v3(x, top, -zf), r, LEGS));
            } else {
                let (front, back) = (v3(x, r, zf), v3(x, r, -zf));
                prims.push(rod(back, front, r, LEGS));
                prims.push(rod(front, v3(x, top, 0.8 * zf), r, LEGS));
                prims.push(rod(back, v3(x, top, -0.8 * zf), r, LEGS));
                prims.push(rod(v3(x, top, 0.8 * zf), v3(x, top, -0.8 * zf), r, LEGS));
            }
        }
        if cantilever {
            prims.push(rod(v3(-x, r, -0.7 * zf), v3(x, r, -0.7 * zf), r, LEGS));
        }
    }

    /// A block under the seat, or a column on a round base.
    fn pedestal(&self, prims: &mut Vec<Prim>, block: bool, base_radius: f32, yb: f32, hw: f32, hd: f32) {
        let round_seat = self.seat == SeatShape::Round;
        if block {
            let (bx, bz) = if round_seat { (0.6 * hw, 0.6 * hw) } else { (0.8 * hw, 0.8 * hd) };
            prims.push(Prim::new(
                Shape::RoundBox { half: v3(bx, yb / 2.0, bz), round: 0.02 },
                Rot::IDENTITY,
                v3(0.0, yb / 2.0, 0.0),
                LEGS,
            ));
        } else {
            let col = 0.04 + 0.15 * base_radius;
            prims.push(Prim::new(
                Shape::Cylinder { radius: col, half_height: yb / 2.0, round: 0.0 },
                Rot::IDENTITY,
                v3(0.0, yb / 2.0, 0.0),
                LEGS,
            ));
            prims.push(Prim::new(
                Shape::Cylinder { radius: base_radius, half_height: 0.015, round: 0.01 },
                Rot::IDENTITY,
                v3(0.0, 0.015, 0.0),
                LEGS,
            ));
        }
    }
}

/// An office chair's base: a plate under the seat, the gas column and its sleeve, a hub and
/// `spokes` spokes of `radius` ending in casters.
fn swivel_base(prims: &mut Vec<Prim>, spokes: u32, radius: f32, yb: f32) {
    let hub_y = 0.08;
    prims.push(Prim::new(
        Shape::RoundBox { half: v3(0.11, 0.015, 0.11), round: 0.005 },
        Rot::IDENTITY,
        v3(0.0, yb - 0.015, 0.0),
        LEGS,
    ));
    let col_lo = hub_y;
    prims.push(Prim::new(
        Shape::Cylinder { radius: 0.022, half_height: (yb - col_lo) / 2.0, round: 0.0 },
        Rot::IDENTITY,
        v3(0.0, (yb + col_lo) / 2.0, 0.0),
        LEGS,
    ));
    prims.push(Prim::new(
        Shape::Cylinder { radius: 0.035, half_height: 0.08, round: 0.005 },
        Rot::IDENTITY,
        v3(0.0, hub_y + 0.08, 0.0),
        LEGS,
    ));
    prims.push(Prim::new(
        Shape::Cylinder { radius: 0.05, half_height: 0.025, round: 0.008 },
        Rot::IDENTITY,
        v3(0.0, hub_y, 0.0),
        LEGS,
    ));
    for i in 0..spokes {
        let (s, c) = (FRAC_PI_2 + TAU * i as f32 / spokes as f32).sin_cos();
        let end = v3(radius * c, 0.06, radius * s);
        prims.push(beam(v3(0.0, hub_y, 0.0), end, 0.018, 0.014, Some(v3(0.0, 1.0, 0.0).cross(v3(c, 0.0, s))), LEGS));
        prims.push(Prim::new(Shape::Sphere { radius: 0.03 }, Rot::IDENTITY, v3(radius * c, 0.03, radius * s), LEGS));
    }
}
