//! Photos as they come, turned into the square `(1, 3, R, R)` images in [−1, 1] that the
//! inversion compares renders with, prepared as the dataset loader prepares training images
//! ([`crate::data::folder`]), with the object's silhouette and its framing ([`framing`]).
//!
//! - **Formats**: PNG and JPEG, decoded by [`folder::decode_rgba`] (grayscale, 16-bit and
//!   palette images through float RGBA; empty, unrecognised, truncated or zero-sized files
//!   are errors).
//! - **Silhouette**: `mask` (a grayscale image of the photo's size; white keeps a pixel,
//!   black turns it into background, grey blends), else the alpha channel, else a uniform
//!   background found on the border ([`framing`]).
//! - **Background**: the photo is composited on white (the renders' background) through its
//!   silhouette.
//! - **Square**: [`Fit::Auto`] (default) frames the object as the training images frame
//!   theirs ([`Framing::window`]) where there is a silhouette and a [`Framing`], else takes
//!   the centred square of the shorter side as [`Fit::Crop`] (the loader's) does;
//!   [`Fit::Pad`] pads the shorter side with white to a square.
//! - **Resizing**: to `R × R` with the loader's area filter ([`folder::area_resize`]).
use super::framing::{self, Framing, ObjectBox, SilhouetteFrom, Window};
use crate::data::folder;
use crate::{Error, Result};
use image::Rgba32FImage;
use std::path::Path;
use tch::{Device, Kind, Tensor};

/// How a photo becomes square.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Fit {
    /// The object framed as in the training images, where the photo has a silhouette and a
    /// framing is known; else as [`Fit::Crop`].
    #[default]
    Auto,
    /// The centred square of the shorter side.
    Crop,
    /// White borders on the shorter side.
    Pad,
}

impl std::str::FromStr for Fit {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "auto" => Ok(Fit::Auto),
            "crop" => Ok(Fit::Crop),
            "pad" => Ok(Fit::Pad),
            _ => Err(Error::Invalid(format!("fit '{s}': expected auto, crop or pad"))),
        }
    }
}

/// A photo ready for the inversion, and what was done to it.
#[derive(Debug)]
pub struct Photo {
    /// `(1, 3, R, R)` float32 in [−1, 1], on white.
    pub rgb: Tensor,
    /// `(1, 1, R, R)` float32 in [0, 1]: the object's share of each pixel, where the photo
    /// has a silhouette.
    pub silhouette: Option<Tensor>,
    pub from: SilhouetteFrom,
    /// The photo's width and height.
    pub size: (u32, u32),
    /// The object's box in the photo, where the silhouette has one.
    pub object: Option<ObjectBox>,
    /// The square of the photo that became the image.
    pub window: Window,
    /// Whether the framing moved the window from the one `--fit crop|pad` takes.
    pub reframed: bool,
    /// What the user should know (no silhouette found; no framing known).
    pub warnings: Vec<String>,
}

impl Photo {
    /// One line on the silhouette and the square taken.
    pub fn describe(&self) -> String {
        let (w, h) = self.size;
        let place = match (self.object, self.reframed) {
            (Some(b), true) => {
                let win = self.window;
                let pad = win.x < 0 || win.y < 0 || win.x + win.side > w as i64 || win.y + win.side > h as i64;
                format!(
                    "; the object ({:.0}×{:.0} px) filled {:.2} of the {}-px square: framed as in the training images, by the {}-px square at ({}, {}){}, where it fills {:.2}",
                    b[2] - b[0],
                    b[3] - b[1],
                    (b[2] - b[0]).max(b[3] - b[1]) / w.min(h) as f64,
                    w.min(h),
                    win.side,
                    win.x,
                    win.y,
                    if pad { ", padded" } else { "" },
                    (b[2] - b[0]).max(b[3] - b[1]) / win.side as f64
                )
            }
            (Some(b), false) => format!(
                "; the object ({:.0}×{:.0} px) sits as in the training images in the {}-px square at ({}, {})",
                b[2] - b[0],
                b[3] - b[1],
                self.window.side,
                self.window.x,
                self.window.y
            ),
            (None, _) => format!("; the {}-px square at ({}, {})", self.window.side, self.window.x, self.window.y),
        };
        format!("photo {w}×{h}: {}{place}", self.from.describe())
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

/// Loads `path` as it is, as a `(1, 3, res, res)` float32 image in [−1, 1] on `device`: its
/// alpha (times `mask`) composited on white, squared by `fit` ([`Fit::Auto`] as
/// [`Fit::Crop`]), with no background found on the border and no framing: as the dataset
/// loader reads a training image.
pub fn load_photo(path: &Path, mask: Option<&Path>, fit: Fit, res: i64, device: Device) -> Result<Tensor> {
    Ok(prepare(path, mask, fit, None, false, res, device)?.rgb)
}

/// Loads `path` with its silhouette, squared by `fit` (framed by `framing` under
/// [`Fit::Auto`]) and resized to `res × res` on `device` (see the module's documentation).
pub fn prepare_photo(
    path: &Path,
    mask: Option<&Path>,
    fit: Fit,
    framing: Option<&Framing>,
    res: i64,
    device: Device,
) -> Result<Photo> {
    prepare(path, mask, fit, framing, true, res, device)
}

/// [`prepare_photo`], finding a uniform background on an opaque photo's border only with
/// `find_background`.
fn prepare(
    path: &Path,
    mask: Option<&Path>,
    fit: Fit,
    framing: Option<&Framing>,
    find_background: bool,
    res: i64,
    device: Device,
) -> Result<Photo> {
    if !(2..=4096).contains(&res) {
        return Err(Error::Invalid(format!("photo resolution {res} is out of range, expected 2 to 4096")));
    }
    let mut rgba = open(path, "photo")?;
    let (w, h) = rgba.dimensions();
    let mut warnings = Vec::new();
    let from = if let Some(mask_path) = mask {
        let m = image::DynamicImage::ImageRgba32F(open(mask_path, "mask")?).to_luma32f();
        if m.dimensions() != rgba.dimensions() {
            return Err(Error::Invalid(format!(
                "mask {} is {}×{} but the photo is {}×{}; expected the same size",
                mask_path.display(),
                m.width(),
                m.height(),
                w,
                h
            )));
        }
        for (p, k) in rgba.pixels_mut().zip(m.pixels()) {
            p.0[3] *= k.0[0].clamp(0.0, 1.0);
        }
        SilhouetteFrom::Mask
    } else if rgba.pixels().any(|p| p.0[3] < 1.0) {
        SilhouetteFrom::Alpha
    } else if !find_background {
        SilhouetteFrom::None
    } else {
        let rgb: Vec<[f32; 3]> = rgba.pixels().map(|p| [p.0[0], p.0[1], p.0[2]].map(|c| c.clamp(0.0, 1.0))).collect();
        match framing::border_background(&rgb, w as usize, h as usize) {
            Some(bg) => {
                for (p, c) in rgba.pixels_mut().zip(&rgb) {
                    p.0[3] = framing::background_silhouette(c, &bg);
                }
                SilhouetteFrom::Background(bg)
            }
            None => {
                warnings.push(format!(
                    "{} has no alpha channel and its border is not one colour, so the object was not found: the photo is not framed and no silhouette is used; give --mask FILE (white = object) to find it",
                    path.display()
                ));
                SilhouetteFrom::None
            }
        }
    };
    let mut alpha: Vec<f32> = rgba.pixels().map(|p| p.0[3].clamp(0.0, 1.0)).collect();
    let object = match from {
        SilhouetteFrom::None => None,
        _ => framing::object_box(&alpha, w as usize, h as usize),
    };
    let from = match (from, object) {
        (SilhouetteFrom::None, _) => SilhouetteFrom::None,
        (f, None) => {
            // A photo of its background colour alone stays as it is; an empty alpha or
            // mask still makes its pixels background.
            if let SilhouetteFrom::Background(_) = f {
                alpha.fill(1.0);
            }
            warnings.push(format!(
                "the {} of {} is empty: the photo is not framed and no silhouette is used",
                f.describe(),
                path.display()
            ));
            SilhouetteFrom::None
        }
        (f, Some(_)) => f,
    };
    let default = match fit {
        Fit::Auto | Fit::Crop => {
            let s = w.min(h) as i64;
            Window { x: (w as i64 - s) / 2, y: (h as i64 - s) / 2, side: s }
        }
        Fit::Pad => {
            let s = w.max(h) as i64;
            Window { x: -((s - w as i64) / 2), y: -((s - h as i64) / 2), side: s }
        }
    };
    let (window, reframed) = match (fit, object, framing) {
        (Fit::Auto, Some(b), Some(f)) => f.window(b, default),
        _ => (default, false),
    };
    // The window's pixels, channel-major (the loader's layout for its area filter), on
    // white and with no object outside the photo.
    let side = window.side as usize;
    let plane = side * side;
    let mut planes = vec![0f32; 4 * plane];
    for y in 0..side {
        for x in 0..side {
            let (px, py) = (window.x + x as i64, window.y + y as i64);
            let i = y * side + x;
            let (c, a) = if px >= 0 && py >= 0 && px < w as i64 && py < h as i64 {
                let p = rgba.get_pixel(px as u32, py as u32).0;
                ([p[0], p[1], p[2]], alpha[py as usize * w as usize + px as usize])
            } else {
                ([1.0; 3], 0.0)
            };
            // Composite on white: c·α + (1 − α).
            for k in 0..3 {
                planes[k * plane + i] = c[k].clamp(0.0, 1.0) * a + (1.0 - a);
            }
            planes[3 * plane + i] = a;
        }
    }
    let resized = folder::area_resize(&planes, 4, side, res as usize);
    let (r, n) = (res, (res * res) as usize);
    let tensor = |v: &[f32], c: i64| Tensor::from_slice(v).view([1, c, r, r]).to_kind(Kind::Float).to_device(device);
    let rgb = tensor(&resized[..3 * n], 3) * 2.0 - 1.0;
    let silhouette = (from != SilhouetteFrom::None).then(|| tensor(&resized[3 * n..], 1));
    Ok(Photo { rgb, silhouette, from, size: (w, h), object, window, reframed, warnings })
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

    fn framing() -> Framing {
        Framing { size: [0.5, 0.8], centre_x: [0.45, 0.55], centre_y: [0.4, 0.6], images: 1, dataset: "t".into() }
    }

    /// Asserts that image `t: (1, C, R, R)` equals `want(x, y)` at every pixel, exactly.
    fn assert_image(t: &Tensor, want: impl Fn(i64, i64) -> Vec<f64>) {
        let r = t.size()[2];
        for y in 0..r {
            for x in 0..r {
                let got: Vec<f64> = Vec::try_from(t.get(0).select(1, y).select(1, x).to_kind(Kind::Double)).unwrap();
                assert_eq!(got, want(x, y), "pixel ({x}, {y})");
            }
        }
    }

    #[test]
    fn framing_from_alpha_crops_exactly() {
        let d = tmp("frame-alpha");
        // 100 × 80, transparent, an opaque blue 20 × 40 block at x 10..30, y 20..60: 40 px
        // long (0.5 of the centred 80-px square, in range), centred at x 20 (0.125 of that
        // square: out of range) → the 80-px square whose 0.45 is x 20: from x −16.
        let mut img = RgbaImage::from_pixel(100, 80, Rgba([0, 0, 0, 0]));
        for y in 20..60 {
            for x in 10..30 {
                img.put_pixel(x, y, Rgba([0, 0, 255, 255]));
            }
        }
        img.save(d.join("p.png")).unwrap();
        let p = prepare_photo(&d.join("p.png"), None, Fit::Auto, Some(&framing()), 80, Device::Cpu).unwrap();
        assert_eq!((p.from, p.object, p.reframed), (SilhouetteFrom::Alpha, Some([10.0, 20.0, 30.0, 60.0]), true));
        assert_eq!(p.window, Window { x: -16, y: 0, side: 80 });
        let inside = |x: i64, y: i64| (26..46).contains(&x) && (20..60).contains(&y);
        assert_image(&p.rgb, |x, y| if inside(x, y) { vec![-1.0, -1.0, 1.0] } else { vec![1.0; 3] });
        assert_image(p.silhouette.as_ref().unwrap(), |x, y| vec![if inside(x, y) { 1.0 } else { 0.0 }]);
        assert!(p.describe().contains("alpha channel") && p.describe().contains("80-px square at (-16, 0), padded"));
        // --fit crop keeps the centred square, with the silhouette.
        let c = prepare_photo(&d.join("p.png"), None, Fit::Crop, Some(&framing()), 80, Device::Cpu).unwrap();
        assert_eq!((c.window, c.reframed), (Window { x: 10, y: 0, side: 80 }, false));
        assert!(c.silhouette.is_some());
        // Without a framing, Auto takes the centred square.
        let n = prepare_photo(&d.join("p.png"), None, Fit::Auto, None, 80, Device::Cpu).unwrap();
        assert_eq!(n.window, c.window);
        std::fs::remove_dir_all(d).ok();
    }

    #[test]
    fn framing_from_a_uniform_background_and_from_a_mask() {
        let d = tmp("frame-bg");
        // Opaque 64², grey background, a red 16² block at x 4..20, y 8..24: 0.25 long → 0.5
        // (side 32); centre (12, 16) at 0.1875, 0.25 → 0.45, 0.4: the square from (−2, 3).
        let mut img = RgbImage::from_pixel(64, 64, Rgb([128, 128, 128]));
        for y in 8..24 {
            for x in 4..20 {
                img.put_pixel(x, y, Rgb([255, 0, 0]));
            }
        }
        img.save(d.join("p.png")).unwrap();
        let p = prepare_photo(&d.join("p.png"), None, Fit::Auto, Some(&framing()), 32, Device::Cpu).unwrap();
        assert_eq!(p.from, SilhouetteFrom::Background([128.0 / 255.0; 3]));
        assert_eq!((p.window, p.object), (Window { x: -2, y: 3, side: 32 }, Some([4.0, 8.0, 20.0, 24.0])));
        // The grey became white; the block sits at x 6..22, y 5..21 of the window.
        let inside = |x: i64, y: i64| (6..22).contains(&x) && (5..21).contains(&y);
        assert_image(&p.rgb, |x, y| if inside(x, y) { vec![1.0, -1.0, -1.0] } else { vec![1.0; 3] });
        assert_image(p.silhouette.as_ref().unwrap(), |x, y| vec![if inside(x, y) { 1.0 } else { 0.0 }]);
        assert!(p.warnings.is_empty());
        // A mask overrides: it keeps only the block's left half (x 4..12: 8 × 16, 0.25 → 0.5,
        // side 32; centre (8, 16) → x 8 − 14.4, y 16 − 12.8), grey and all.
        let mut m = GrayImage::from_pixel(64, 64, Luma([0]));
        for y in 8..24 {
            for x in 4..12 {
                m.put_pixel(x, y, Luma([255]));
            }
        }
        m.save(d.join("m.png")).unwrap();
        let q = prepare_photo(&d.join("p.png"), Some(&d.join("m.png")), Fit::Auto, Some(&framing()), 32, Device::Cpu)
            .unwrap();
        assert_eq!((q.from, q.object), (SilhouetteFrom::Mask, Some([4.0, 8.0, 12.0, 24.0])));
        assert_eq!(q.window, Window { x: -6, y: 3, side: 32 });
        let inside = |x: i64, y: i64| (10..18).contains(&x) && (5..21).contains(&y);
        assert_image(&q.rgb, |x, y| if inside(x, y) { vec![1.0, -1.0, -1.0] } else { vec![1.0; 3] });
        std::fs::remove_dir_all(d).ok();
    }

    #[test]
    fn a_photo_without_a_silhouette_is_centre_cropped_with_a_warning_naming_mask() {
        let d = tmp("frame-none");
        // Left half black, right half white: the border is two colours.
        let mut img = RgbImage::from_pixel(8, 6, Rgb([255, 255, 255]));
        for y in 0..6 {
            for x in 0..4 {
                img.put_pixel(x, y, Rgb([0, 0, 0]));
            }
        }
        img.save(d.join("p.jpg")).unwrap();
        let p = prepare_photo(&d.join("p.jpg"), None, Fit::Auto, Some(&framing()), 6, Device::Cpu).unwrap();
        assert_eq!(
            (p.from, p.silhouette.is_none(), p.window),
            (SilhouetteFrom::None, true, Window { x: 1, y: 0, side: 6 })
        );
        assert!(p.warnings.len() == 1 && p.warnings[0].contains("--mask"), "{:?}", p.warnings);
        // A photo of one colour alone has an empty silhouette and stays as it is.
        RgbImage::from_pixel(4, 4, Rgb([0, 255, 0])).save(d.join("flat.png")).unwrap();
        let f = prepare_photo(&d.join("flat.png"), None, Fit::Auto, Some(&framing()), 4, Device::Cpu).unwrap();
        assert_eq!(f.from, SilhouetteFrom::None);
        assert_image(&f.rgb, |_, _| vec![-1.0, 1.0, -1.0]);
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
        assert_eq!("auto".parse::<Fit>().unwrap(), Fit::Auto);
        std::fs::remove_dir_all(d).ok();
    }
}
