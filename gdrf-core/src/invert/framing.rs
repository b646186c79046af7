//! Where the object is in a photo, and the square of it that frames the object as the
//! training images frame theirs.
//!
//! - **Silhouette** ([`SilhouetteFrom`]): `--mask` where given (white keeps a pixel), else
//!   the photo's alpha where some pixel is not opaque, else a uniform background estimated
//!   from the photo's border (the per-channel median of its outermost ring of pixels, taken
//!   when [`UNIFORM_SHARE`] of them lie within [`BORDER_TOLERANCE`] of it). A pixel's
//!   silhouette then ramps from 0 within [`BACKGROUND_NEAR`] of the background colour to 1
//!   beyond [`BACKGROUND_FAR`]. A photo with none of the three has no silhouette.
//! - **Framing** ([`Framing`]): the training images' objects sit in a measured range of sizes
//!   and places (`framing.json` beside the generator, from `gdrf-invert framing`). An object
//!   already in that range is left where it is, in the square that `--fit crop|pad` would
//!   take; one outside it gets the nearest placement in the range: the photo is cropped, or
//!   padded with background, to the square that gives it. So a training-like photo is
//!   framed exactly as before, and a small, large or off-centre object is moved no further
//!   than the range.
pub use crate::data::folder::{object_box, ObjectBox};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The most a border pixel may differ from the border's median colour (largest channel
/// difference, colours in [0, 1]) to count as background.
pub const BORDER_TOLERANCE: f32 = 0.1;
/// The share of border pixels that must count as background for the border to be uniform
/// (an object may touch the border).
pub const UNIFORM_SHARE: f64 = 0.9;
/// Within this distance of the background colour (largest channel difference) a pixel is
/// background: JPEG noise and faint vignetting stay out of the silhouette.
pub const BACKGROUND_NEAR: f32 = 0.05;
/// From this distance on a pixel is object; between the two its silhouette ramps linearly.
pub const BACKGROUND_FAR: f32 = 0.15;
/// The range [`Framing`] keeps of each measure over the training images: the 1st to the
/// 99th percentile, so that nearly every training-like photo is left as it is and a rare
/// outlier does not widen the range.
pub const FRAMING_PERCENTILES: [f64; 2] = [1.0, 99.0];
/// The file beside a generator that holds its training images' framing.
pub const FRAMING_FILE: &str = "framing.json";

/// Where a photo's silhouette came from.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SilhouetteFrom {
    /// `--mask`.
    Mask,
    /// The photo's alpha channel.
    Alpha,
    /// A uniform background of this colour (RGB in [0, 1]), estimated from the border.
    Background([f32; 3]),
    /// None: no mask, an opaque photo and a border of several colours.
    None,
}

impl SilhouetteFrom {
    pub fn describe(&self) -> String {
        match self {
            SilhouetteFrom::Mask => "silhouette from --mask".into(),
            SilhouetteFrom::Alpha => "silhouette from the alpha channel".into(),
            SilhouetteFrom::Background(c) => format!(
                "silhouette from the uniform background (RGB {:.0}, {:.0}, {:.0}), which becomes white",
                c[0] * 255.0,
                c[1] * 255.0,
                c[2] * 255.0
            ),
            SilhouetteFrom::None => "no silhouette".into(),
        }
    }
}

/// A square of the photo in pixels, `(x, y)` its top-left corner; it may reach outside the
/// photo, where it holds background.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct Window {
    pub x: i64,
    pub y: i64,
    pub side: i64,
}

/// The placement of the objects in the training images: each measure's range over them
/// ([`FRAMING_PERCENTILES`]), as shares of the image's side.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Framing {
    /// The object's box's longer side.
    pub size: [f64; 2],
    /// The box's centre from the left edge.
    pub centre_x: [f64; 2],
    /// The box's centre from the top edge.
    pub centre_y: [f64; 2],
    /// The images measured, and where they are.
    pub images: usize,
    pub dataset: String,
}

fn within(v: f64, r: [f64; 2]) -> bool {
    v >= r[0] && v <= r[1]
}

/// The `p`-th percentile (0–100) of `v` by linear interpolation between order statistics.
fn percentile(v: &mut [f64], p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    let at = p / 100.0 * (v.len() - 1) as f64;
    let (lo, hi) = (at.floor() as usize, at.ceil() as usize);
    v[lo] + (v[hi] - v[lo]) * (at - lo as f64)
}

impl Framing {
    /// The range of the boxes of silhouettes `(side, alpha plane)` (each the square
    /// training image's alpha, row-major, in [0, 1]); images with an empty silhouette are
    /// not counted.
    pub fn measure<'a>(alphas: impl IntoIterator<Item = (usize, &'a [f32])>, dataset: &str) -> crate::Result<Self> {
        let (mut size, mut cx, mut cy) = (Vec::new(), Vec::new(), Vec::new());
        for (side, alpha) in alphas {
            if let Some(b) = object_box(alpha, side, side) {
                let s = side as f64;
                size.push((b[2] - b[0]).max(b[3] - b[1]) / s);
                cx.push((b[0] + b[2]) / 2.0 / s);
                cy.push((b[1] + b[3]) / 2.0 / s);
            }
        }
        if size.is_empty() {
            return Err(crate::Error::Invalid(format!(
                "{dataset}: no image with a silhouette to measure the framing on"
            )));
        }
        let range = |v: &mut Vec<f64>| FRAMING_PERCENTILES.map(|p| percentile(v, p));
        Ok(Self {
            size: range(&mut size),
            centre_x: range(&mut cx),
            centre_y: range(&mut cy),
            images: size.len(),
            dataset: dataset.into(),
        })
    }

    /// The framing file of `generator`: [`FRAMING_FILE`] beside it.
    pub fn file_beside(generator: &Path) -> std::path::PathBuf {
        generator.with_file_name(FRAMING_FILE)
    }

    /// The framing beside `generator` ([`Framing::file_beside`]), `None` where there is none.
    pub fn beside(generator: &Path) -> crate::Result<Option<Self>> {
        let p = Self::file_beside(generator);
        if !p.is_file() {
            return Ok(None);
        }
        let bad = |reason: String| crate::Error::Data { path: p.clone(), reason };
        let text = std::fs::read_to_string(&p).map_err(|e| bad(format!("cannot read it: {e}")))?;
        let f: Self = serde_json::from_str(&text).map_err(|e| bad(format!("not a framing file: {e}")))?;
        let ordered = |r: [f64; 2]| r[0].is_finite() && r[1].is_finite() && r[0] <= r[1];
        if !(ordered(f.size) && ordered(f.centre_x) && ordered(f.centre_y) && f.size[0] > 0.0) {
            return Err(bad("its ranges must be finite, ordered, and its sizes positive".into()));
        }
        Ok(Some(f))
    }

    /// The window that places `object` (pixels) as the training images place theirs:
    /// `default` when the object lies inside it already placed within the ranges, else
    /// the square that gives it the nearest size and centre in the ranges (rounded to
    /// whole pixels). Also whether it differs from `default`.
    pub fn window(&self, object: ObjectBox, default: Window) -> (Window, bool) {
        let [x0, y0, x1, y1] = object;
        let s = default.side as f64;
        let long = (x1 - x0).max(y1 - y0);
        let (cx, cy) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
        let (size, u, v) = (long / s, (cx - default.x as f64) / s, (cy - default.y as f64) / s);
        let inside = x0 >= default.x as f64
            && y0 >= default.y as f64
            && x1 <= (default.x + default.side) as f64
            && y1 <= (default.y + default.side) as f64;
        if inside && within(size, self.size) && within(u, self.centre_x) && within(v, self.centre_y) {
            return (default, false);
        }
        let clamp = |v: f64, r: [f64; 2]| v.clamp(r[0], r[1]);
        let side = (long / clamp(size, self.size)).round().max(1.0);
        let x = (cx - clamp(u, self.centre_x) * side).round() as i64;
        let y = (cy - clamp(v, self.centre_y) * side).round() as i64;
        let w = Window { x, y, side: side as i64 };
        (w, w != default)
    }
}

/// The uniform background colour of an opaque `w × h` RGB image (row-major pixels in [0, 1]),
/// estimated from its outermost ring of pixels; `None` when the ring is not uniform.
pub fn border_background(rgb: &[[f32; 3]], w: usize, h: usize) -> Option<[f32; 3]> {
    let ring: Vec<[f32; 3]> = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .filter(|&(x, y)| x == 0 || y == 0 || x + 1 == w || y + 1 == h)
        .map(|(x, y)| rgb[y * w + x])
        .collect();
    let median = |c: usize| {
        let mut v: Vec<f64> = ring.iter().map(|p| p[c] as f64).collect();
        percentile(&mut v, 50.0) as f32
    };
    let bg = [median(0), median(1), median(2)];
    let near = ring.iter().filter(|p| distance(p, &bg) <= BORDER_TOLERANCE).count();
    (near as f64 >= UNIFORM_SHARE * ring.len() as f64).then_some(bg)
}

/// Largest channel difference of two colours.
fn distance(a: &[f32; 3], b: &[f32; 3]) -> f32 {
    (0..3).map(|c| (a[c] - b[c]).abs()).fold(0.0, f32::max)
}

/// The silhouette of a pixel of colour `p` against background `bg`: 0 within
/// [`BACKGROUND_NEAR`], 1 from [`BACKGROUND_FAR`], linear between.
pub fn background_silhouette(p: &[f32; 3], bg: &[f32; 3]) -> f32 {
    ((distance(p, bg) - BACKGROUND_NEAR) / (BACKGROUND_FAR - BACKGROUND_NEAR)).clamp(0.0, 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn framing() -> Framing {
        Framing { size: [0.5, 0.8], centre_x: [0.45, 0.55], centre_y: [0.4, 0.6], images: 1, dataset: "test".into() }
    }

    #[test]
    fn an_object_in_range_keeps_the_default_window() {
        let d = Window { x: 10, y: 0, side: 80 };
        // 48 px long (0.6), centred at (50, 40): (0.5, 0.5).
        let (w, moved) = framing().window([26.0, 16.0, 74.0, 64.0], d);
        assert_eq!((w, moved), (d, false));
    }

    #[test]
    fn a_small_off_centre_object_is_brought_to_the_nearest_placement() {
        let d = Window { x: 0, y: 0, side: 100 };
        // 20 × 10 px at the top left: size 0.2 → 0.5, so the side is 40; the centre (15, 10)
        // sits at 0.45 and 0.4 of it.
        let (w, moved) = framing().window([5.0, 5.0, 25.0, 15.0], d);
        assert!(moved);
        assert_eq!(w, Window { x: 15 - 18, y: 10 - 16, side: 40 });
    }

    #[test]
    fn a_large_object_is_padded_to_the_largest_size() {
        let d = Window { x: 0, y: 0, side: 100 };
        // 96 px long, centred: 0.96 → 0.8, side 120, centred.
        let (w, _) = framing().window([2.0, 10.0, 98.0, 90.0], d);
        assert_eq!(w, Window { x: 50 - 60, y: 50 - 60, side: 120 });
    }

    #[test]
    fn boxes_borders_and_percentiles() {
        let mut a = vec![0f32; 6 * 4];
        assert_eq!(object_box(&a, 6, 4), None);
        a[6 + 2] = 1.0;
        a[2 * 6 + 4] = 0.6;
        a[3 * 6] = 0.5; // not above the threshold
        assert_eq!(object_box(&a, 6, 4), Some([2.0, 1.0, 5.0, 3.0]));
        let mut v = vec![4.0, 1.0, 3.0, 2.0];
        assert_eq!(percentile(&mut v, 50.0), 2.5);
        assert_eq!(percentile(&mut v, 0.0), 1.0);
        // A grey ring with one red pixel in it (1 of 12: under the tolerated tenth) is uniform.
        let mut rgb = vec![[0.5f32; 3]; 16];
        rgb[1] = [1.0, 0.0, 0.0];
        assert_eq!(border_background(&rgb, 4, 4), Some([0.5; 3]));
        rgb[2] = [1.0, 0.0, 0.0];
        assert_eq!(border_background(&rgb, 4, 4), None);
        assert_eq!(background_silhouette(&[0.54, 0.5, 0.5], &[0.5; 3]), 0.0);
        assert_eq!(background_silhouette(&[0.5, 0.5, 0.7], &[0.5; 3]), 1.0);
        assert!((background_silhouette(&[0.6, 0.5, 0.5], &[0.5; 3]) - 0.5).abs() < 1e-5);
    }

    #[test]
    fn measured_ranges_are_the_percentiles_of_the_boxes() {
        // Three 10² images with boxes 4, 6 and 8 px long, centred at 0.5.
        let planes: Vec<Vec<f32>> = [4usize, 6, 8]
            .iter()
            .map(|&n| {
                let mut a = vec![0f32; 100];
                let o = (10 - n) / 2;
                for y in o..o + n {
                    for x in o..o + n {
                        a[y * 10 + x] = 1.0;
                    }
                }
                a
            })
            .collect();
        let f = Framing::measure(planes.iter().map(|p| (10, p.as_slice())), "d").unwrap();
        assert_eq!(f.images, 3);
        // The 1st and 99th percentiles: 0.4 + 0.2 · 0.02 and 0.6 + 0.2 · 0.98.
        assert!((f.size[0] - 0.404).abs() < 1e-12 && (f.size[1] - 0.796).abs() < 1e-12, "{:?}", f.size);
        assert_eq!((f.centre_x, f.centre_y), ([0.5, 0.5], [0.5, 0.5]));
        assert!(Framing::measure([(10usize, &[0f32; 100][..])], "empty").is_err());
    }
}
