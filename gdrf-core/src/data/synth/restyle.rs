//! Photos of an object as the house style never frames them: in a wider or taller frame, at
//! another scale and place, on a uniform background that is not white (off-white, grey or
//! coloured), opaque (no alpha) and JPEG-compressed. Each is drawn from its own random
//! stream of (seed, object), so the same seed always gives the same photo; one seed range
//! chooses settings, another reports.
//!
//! Materials and lighting stay the house style's: the ground truth of the object's novel
//! views is then still the dataset's own renders.
use super::render::Rendered;
use super::rng::{object_seed, Rng, Stream};
use crate::{Error, Result};
use serde::Serialize;

/// How one photo is framed and finished.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Restyle {
    /// The frame's width and height in pixels.
    pub frame: (u32, u32),
    /// The object's box's longer side, as a share of the frame's shorter side.
    pub size: f64,
    /// The box's centre, as shares of the frame's width and height.
    pub centre: (f64, f64),
    /// The background colour (sRGB bytes).
    pub background: [u8; 3],
    /// JPEG quality (1–100).
    pub quality: u8,
}

/// The frames' aspect ratios (width / height).
const ASPECTS: [f64; 4] = [1.0, 4.0 / 3.0, 3.0 / 4.0, 16.0 / 9.0];

impl Restyle {
    /// The style of object `index` under `seed`: a frame of aspect 1, 4:3, 3:4 or 16:9 with
    /// a shorter side of 96–192 px; the object 0.3–0.95 of that side long, placed anywhere it
    /// fits whole; an off-white, grey or coloured background; JPEG quality 60–95.
    pub fn draw(seed: u64, index: u64) -> Self {
        let mut rng = Rng::new(object_seed(seed, index), Stream::Restyle);
        let aspect = ASPECTS[rng.int(0, ASPECTS.len() as u32 - 1) as usize];
        let short = rng.int(96, 192) as f64;
        let frame = if aspect >= 1.0 {
            ((short * aspect).round() as u32, short as u32)
        } else {
            (short as u32, (short / aspect).round() as u32)
        };
        let size = rng.range(0.3, 0.95);
        // The centre leaves half the box's longer side to each edge.
        let half = size * short / 2.0;
        let mut place = |side: u32| {
            let s = side as f64;
            rng.range(half / s, 1.0 - half / s)
        };
        let centre = (place(frame.0), place(frame.1));
        let background = match rng.int(0, 2) {
            0 => [rng.int(232, 250) as u8; 3],
            1 => [rng.int(80, 200) as u8; 3],
            _ => {
                let hue = rng.range(0.0, 6.0);
                let (sat, val) = (rng.range(0.25, 0.6), rng.range(0.5, 0.9));
                hsv_bytes(hue, sat, val)
            }
        };
        let quality = rng.int(60, 95) as u8;
        Self { frame, size, centre, background, quality }
    }

    /// The photo of `rendered` (one object, its straight alpha) in this style, as JPEG bytes:
    /// the object's box scaled to [`Restyle::size`] and centred at [`Restyle::centre`]
    /// (bilinear resampling), composited on the background.
    pub fn photo(&self, rendered: &Rendered) -> Result<Vec<u8>> {
        let r = rendered.resolution;
        let b = crate::data::folder::object_box(&rendered.alpha, r, r)
            .ok_or_else(|| Error::Invalid("the rendered object is empty".into()))?;
        let (w, h) = self.frame;
        let short = w.min(h) as f64;
        // Photo pixels per rendered pixel, and the rendered point at the photo's origin.
        let k = self.size * short / (b[2] - b[0]).max(b[3] - b[1]);
        let origin =
            ((b[0] + b[2]) / 2.0 - self.centre.0 * w as f64 / k, (b[1] + b[3]) / 2.0 - self.centre.1 * h as f64 / k);
        let bg = self.background.map(|c| c as f32 / 255.0);
        let mut img = image::RgbImage::new(w, h);
        for (x, y, p) in img.enumerate_pixels_mut() {
            // The pixel's centre in rendered pixel coordinates (centres at i + ½).
            let u = origin.0 + (x as f64 + 0.5) / k - 0.5;
            let v = origin.1 + (y as f64 + 0.5) / k - 0.5;
            let (c, a) = bilinear(rendered, u, v);
            // The render is composited on white: c·α + (1 − α); on the background instead.
            p.0 = [0, 1, 2].map(|i| ((c[i] + (bg[i] - 1.0) * (1.0 - a)).clamp(0.0, 1.0) * 255.0).round() as u8);
        }
        let mut bytes = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, self.quality)
            .encode_image(&img)
            .map_err(|e| Error::Invalid(format!("JPEG encoding failed: {e}")))?;
        Ok(bytes)
    }
}

/// The colour (composited on white) and alpha of `r` at pixel coordinates `(u, v)`, bilinear
/// between pixel centres; outside the render, white and transparent.
fn bilinear(r: &Rendered, u: f64, v: f64) -> ([f32; 3], f32) {
    let n = r.resolution as i64;
    let (x0, y0) = (u.floor() as i64, v.floor() as i64);
    let (fx, fy) = ((u - x0 as f64) as f32, (v - y0 as f64) as f32);
    let mut c = [0f32; 3];
    let mut a = 0f32;
    for (dx, dy, wgt) in
        [(0, 0, (1.0 - fx) * (1.0 - fy)), (1, 0, fx * (1.0 - fy)), (0, 1, (1.0 - fx) * fy), (1, 1, fx * fy)]
    {
        let (x, y) = (x0 + dx, y0 + dy);
        let (px, pa) = if x >= 0 && y >= 0 && x < n && y < n {
            let i = (y * n + x) as usize;
            ([r.rgb[3 * i], r.rgb[3 * i + 1], r.rgb[3 * i + 2]], r.alpha[i])
        } else {
            ([1.0; 3], 0.0)
        };
        for k in 0..3 {
            c[k] += wgt * px[k];
        }
        a += wgt * pa;
    }
    (c, a)
}

/// sRGB bytes of hue `h` in [0, 6), saturation and value in [0, 1].
fn hsv_bytes(h: f64, s: f64, v: f64) -> [u8; 3] {
    super::material::hsv((h / 6.0) as f32, s as f32, v as f32).map(|c| (c * 255.0).round() as u8)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 16² render: a black 4 × 8 block at x 6..10, y 4..12, on white.
    fn block() -> Rendered {
        let n = 16;
        let mut rgb = vec![1f32; 3 * n * n];
        let mut alpha = vec![0f32; n * n];
        for y in 4..12 {
            for x in 6..10 {
                let i = y * n + x;
                alpha[i] = 1.0;
                rgb[3 * i..3 * i + 3].fill(0.0);
            }
        }
        Rendered { resolution: n, rgb, alpha, parts: vec![0.0; n * n * 4] }
    }

    #[test]
    fn the_same_seed_draws_the_same_photo_and_another_seed_another() {
        let r = block();
        let (a, b) = (Restyle::draw(7, 3), Restyle::draw(7, 3));
        assert_eq!(a, b);
        assert_eq!(a.photo(&r).unwrap(), b.photo(&r).unwrap());
        assert_ne!(Restyle::draw(8, 3), a);
        assert_ne!(Restyle::draw(7, 4), a);
        for i in 0..200 {
            let s = Restyle::draw(1, i);
            let short = s.frame.0.min(s.frame.1) as f64;
            assert!((96.0..=192.0).contains(&short) && (0.3..0.95).contains(&s.size) && (60..=95).contains(&s.quality));
            // The object fits whole in the frame.
            let half = s.size * short / 2.0;
            assert!(
                s.centre.0 * s.frame.0 as f64 >= half - 1e-9 && (1.0 - s.centre.0) * s.frame.0 as f64 >= half - 1e-9
            );
            assert!(
                s.centre.1 * s.frame.1 as f64 >= half - 1e-9 && (1.0 - s.centre.1) * s.frame.1 as f64 >= half - 1e-9
            );
        }
    }

    #[test]
    fn the_object_lands_at_its_size_and_place_on_the_background() {
        // A 100 × 80 frame, the 8-px block made 40 px long (0.5 of 80), centred at (30, 40).
        let s = Restyle { frame: (100, 80), size: 0.5, centre: (0.3, 0.5), background: [0, 128, 255], quality: 100 };
        let photo = image::load_from_memory(&s.photo(&block()).unwrap()).unwrap().to_rgb8();
        assert_eq!(photo.dimensions(), (100, 80));
        // The block spans x 20..40 (20 wide), y 20..60: black inside, the background outside
        // (to JPEG's rounding at quality 100).
        let near = |p: [u8; 3], q: [u8; 3]| (0..3).all(|i| (p[i] as i32 - q[i] as i32).abs() <= 6);
        assert!(near(photo.get_pixel(30, 40).0, [0, 0, 0]), "{:?}", photo.get_pixel(30, 40));
        assert!(near(photo.get_pixel(22, 22).0, [0, 0, 0]));
        assert!(near(photo.get_pixel(5, 5).0, [0, 128, 255]), "{:?}", photo.get_pixel(5, 5));
        assert!(near(photo.get_pixel(80, 40).0, [0, 128, 255]));
        assert!(near(photo.get_pixel(30, 70).0, [0, 128, 255]));
    }
}
