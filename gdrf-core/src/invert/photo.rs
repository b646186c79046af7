//! Photos as they come, turned into the square `(1, 3, R, R)` images in [−1, 1] that the
//! inversion compares renders with, prepared as the dataset loader prepares training images
//! ([`crate::data::folder`]).
//!
//! - **Formats**: PNG and JPEG, decoded by [`folder::decode_rgba`] (grayscale, 16-bit and
//!   palette images through float RGBA; empty, unrecognised, truncated or zero-sized files
//!   are errors).
//! - **Transparency**: RGBA is composited on white (the renders' background).
//! - **`mask`**: a grayscale image of the photo's size; white keeps a pixel, black turns it
//!   into background (white), grey blends.
//! - **Non-square photos**: [`Fit::Crop`] (default, as the loader) keeps the centred square
//!   of the shorter side; [`Fit::Pad`] pads the shorter side with white to a square.
//! - **Resizing**: to `R × R` with the loader's area filter ([`folder::area_resize`]).
use crate::data::folder;
use crate::{Error, Result};
use image::{imageops, Rgba32FImage};
use std::path::Path;
use tch::{Device, Kind, Tensor};

/// How a non-square photo becomes square.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Fit {
    /// The centred square of the shorter side.
    #[default]
    Crop,
    /// White borders on the shorter side.
    Pad,
}

impl std::str::FromStr for Fit {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "crop" => Ok(Fit::Crop),
            "pad" => Ok(Fit::Pad),
            _ => Err(Error::Invalid(format!("fit '{s}': expected crop or pad"))),
        }
    }
}

/// [`folder::decode_rgba`], with a plain message for a missing file; `what` names the input.
fn open(path: &Path, what: &str) -> Result<Rgba32FImage> {
    let input = |reason: String| Error::Data { path: path.to_path_buf(), reason: format!("{reason} (the {what})") };
    if !path.is_file() {
        return Err(input("no such file".into()));
    }
    folder::decode_rgba(path).map_err(|e| match e {
        Error::Data { reason, .. } => input(reason),
        e => e,
    })
}

/// Loads `path` as a `(1, 3, res, res)` float32 image in [−1, 1] on `device` (see the
/// module's documentation for formats, alpha, `mask` and `fit`).
pub fn load_photo(path: &Path, mask: Option<&Path>, fit: Fit, res: i64, device: Device) -> Result<Tensor> {
    if !(2..=4096).contains(&res) {
        return Err(Error::Invalid(format!("photo resolution {res} is out of range, expected 2 to 4096")));
    }
    let mut rgba = open(path, "photo")?;
    if let Some(mask_path) = mask {
        let m = image::DynamicImage::ImageRgba32F(open(mask_path, "mask")?).to_luma32f();
        if m.dimensions() != rgba.dimensions() {
            return Err(Error::Invalid(format!(
                "mask {} is {}×{} but the photo is {}×{}; expected the same size",
                mask_path.display(),
                m.width(),
                m.height(),
                rgba.width(),
                rgba.height()
            )));
        }
        for (p, k) in rgba.pixels_mut().zip(m.pixels()) {
            p.0[3] *= k.0[0].clamp(0.0, 1.0);
        }
    }
    // Composite on white: c·α + (1 − α).
    for p in rgba.pixels_mut() {
        let a = p.0[3].clamp(0.0, 1.0);
        for c in 0..3 {
            p.0[c] = p.0[c].clamp(0.0, 1.0) * a + (1.0 - a);
        }
        p.0[3] = 1.0;
    }
    let square = squared(&rgba, fit);
    let side = square.width() as usize;
    // Channel-major planes, the loader's layout for its area filter.
    let mut planes = vec![0f32; 3 * side * side];
    for (i, p) in square.pixels().enumerate() {
        for c in 0..3 {
            planes[c * side * side + i] = p.0[c];
        }
    }
    let resized = folder::area_resize(&planes, 3, side, res as usize);
    Ok(Tensor::from_slice(&resized).view([1, 3, res, res]).to_kind(Kind::Float).to_device(device) * 2.0 - 1.0)
}

fn squared(img: &Rgba32FImage, fit: Fit) -> Rgba32FImage {
    let (w, h) = img.dimensions();
    if w == h {
        return img.clone();
    }
    match fit {
        Fit::Crop => {
            let s = w.min(h);
            imageops::crop_imm(img, (w - s) / 2, (h - s) / 2, s, s).to_image()
        }
        Fit::Pad => {
            let s = w.max(h);
            let mut out = Rgba32FImage::from_pixel(s, s, image::Rgba([1.0, 1.0, 1.0, 1.0]));
            imageops::replace(&mut out, img, ((s - w) / 2) as i64, ((s - h) / 2) as i64);
            out
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::{GrayImage, ImageBuffer, Luma, Rgb, RgbImage, Rgba, RgbaImage};

    fn tmp(name: &str) -> std::path::PathBuf {
        let d = std::env::temp_dir().join(format!("gdrf-photo-{}-{name}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    fn px(t: &Tensor, y: i64, x: i64) -> [f64; 3] {
        let v: Vec<f64> = Vec::try_from(t.get(0).select(1, y).select(1, x).to_kind(Kind::Double)).unwrap();
        [v[0], v[1], v[2]]
    }

    #[test]
    fn formats_alpha_mask_and_fit() {
        let d = tmp("formats");
        // RGBA: a transparent pixel becomes white, an opaque red stays red.
        let mut rgba = RgbaImage::from_pixel(4, 4, Rgba([255, 0, 0, 255]));
        rgba.put_pixel(0, 0, Rgba([0, 0, 0, 0]));
        rgba.save(d.join("a.png")).unwrap();
        let t = load_photo(&d.join("a.png"), None, Fit::Crop, 4, Device::Cpu).unwrap();
        assert_eq!(t.size(), [1, 3, 4, 4]);
        assert_eq!(px(&t, 0, 0), [1.0, 1.0, 1.0]);
        assert_eq!(px(&t, 2, 2), [1.0, -1.0, -1.0]);
        // 16-bit grayscale: mid grey 32768/65535 → 2·0.500008 − 1.
        let g16: ImageBuffer<Luma<u16>, Vec<u16>> = ImageBuffer::from_pixel(3, 3, Luma([32768]));
        g16.save(d.join("g16.png")).unwrap();
        let t = load_photo(&d.join("g16.png"), None, Fit::Crop, 3, Device::Cpu).unwrap();
        let want = 2.0 * 32768.0 / 65535.0 - 1.0;
        for c in px(&t, 1, 1) {
            assert!((c - want).abs() < 1e-6, "{c} vs {want}");
        }
        // Non-square 6×2, left half black, right half white: the crop keeps the middle 2×2
        // (one black, one white column); the pad keeps all with white rows above and below.
        let mut wide = RgbImage::from_pixel(6, 2, Rgb([255, 255, 255]));
        for y in 0..2 {
            for x in 0..3 {
                wide.put_pixel(x, y, Rgb([0, 0, 0]));
            }
        }
        wide.save(d.join("wide.png")).unwrap();
        let c = load_photo(&d.join("wide.png"), None, Fit::Crop, 2, Device::Cpu).unwrap();
        assert_eq!(px(&c, 0, 0), [-1.0; 3]);
        assert_eq!(px(&c, 0, 1), [1.0; 3]);
        let p = load_photo(&d.join("wide.png"), None, Fit::Pad, 6, Device::Cpu).unwrap();
        assert_eq!(px(&p, 0, 0), [1.0; 3]);
        assert_eq!(px(&p, 2, 0), [-1.0; 3]);
        assert_eq!(px(&p, 5, 0), [1.0; 3]);
        // A mask turns black pixels into background.
        let mut m = GrayImage::from_pixel(6, 2, Luma([255]));
        m.put_pixel(0, 0, Luma([0]));
        m.save(d.join("m.png")).unwrap();
        let t = load_photo(&d.join("wide.png"), Some(&d.join("m.png")), Fit::Pad, 6, Device::Cpu).unwrap();
        assert_eq!(px(&t, 2, 0), [1.0; 3]);
        assert_eq!(px(&t, 3, 0), [-1.0; 3]);
        std::fs::remove_dir_all(d).ok();
    }

    #[test]
    fn bad_photos_are_named() {
        let d = tmp("bad");
        std::fs::write(d.join("junk.png"), b"not an image").unwrap();
        std::fs::write(d.join("empty.png"), b"").unwrap();
        RgbImage::new(4, 4).save(d.join("ok.png")).unwrap();
        // A JPEG cut before its end-of-image marker (the decoder would fill it with grey).
        RgbImage::from_pixel(16, 16, Rgb([200, 10, 10])).save(d.join("whole.jpg")).unwrap();
        let jpeg = std::fs::read(d.join("whole.jpg")).unwrap();
        std::fs::write(d.join("cut.jpg"), &jpeg[..jpeg.len() - 2]).unwrap();
        RgbImage::new(3, 4).save(d.join("small-mask.png")).unwrap();
        let cases = [
            (d.join("missing.png"), None, "no such file"),
            (d.join("junk.png"), None, "not a PNG or JPEG"),
            (d.join("empty.png"), None, "empty file"),
            (d.join("cut.jpg"), None, "truncated JPEG"),
            (d.join("ok.png"), Some(d.join("small-mask.png")), "same size"),
        ];
        for (p, m, want) in cases {
            let e = load_photo(&p, m.as_deref(), Fit::Crop, 8, Device::Cpu).unwrap_err().to_string();
            assert!(e.contains(want) && e.contains(d.to_str().unwrap()), "{e}");
        }
        assert!(load_photo(&d.join("ok.png"), None, Fit::Crop, 0, Device::Cpu).is_err());
        assert!("stretch".parse::<Fit>().is_err());
        std::fs::remove_dir_all(d).ok();
    }
}
