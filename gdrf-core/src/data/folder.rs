//! Decoding one image file to the training format, and listing a folder of images.
//!
//! Every image becomes `3 × R × R` 8-bit RGB on white and its `R × R` alpha: decoded (PNG
//! or JPEG; grayscale, palette, 16-bit and alpha variants included) to float RGBA,
//! composited on white with its alpha, centre-cropped to a square (the shorter side; the
//! longer one loses equal margins) and resized with an area filter (each output pixel is
//! the exact area-weighted mean of the input pixels it covers).
use crate::{Error, Result};
use std::path::{Path, PathBuf};

/// File extensions taken as images (case-insensitive).
pub const IMAGE_EXTENSIONS: [&str; 3] = ["png", "jpg", "jpeg"];

pub fn is_image(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| IMAGE_EXTENSIONS.iter().any(|x| x.eq_ignore_ascii_case(e)))
}

/// Image files directly inside `dir` (not in subfolders), sorted by name.
pub fn list_images(dir: &Path) -> Result<Vec<PathBuf>> {
    let io = |source| Error::Io { path: dir.to_path_buf(), err: source };
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(io)? {
        let path = entry.map_err(io)?.path();
        // Dangling links and unreadable entries are listed too, so that they fail loudly
        // when read instead of vanishing from the dataset.
        if is_image(&path) && !path.is_dir() {
            out.push(path);
        }
    }
    out.sort();
    Ok(out)
}

/// A pixel whose silhouette (alpha) exceeds this belongs to the object's box.
pub const BOX_THRESHOLD: f32 = 0.5;

/// An object's box in pixels: `[x0, y0, x1, y1]`, edges (x1 − x0 pixels wide).
pub type ObjectBox = [f64; 4];

/// The box of the pixels of `alpha` (`w × h`, row-major) above [`BOX_THRESHOLD`], `None`
/// when there are none.
pub fn object_box(alpha: &[f32], w: usize, h: usize) -> Option<ObjectBox> {
    let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
    for y in 0..h {
        for x in 0..w {
            if alpha[y * w + x] > BOX_THRESHOLD {
                x0 = x0.min(x);
                y0 = y0.min(y);
                x1 = x1.max(x + 1);
                y1 = y1.max(y + 1);
            }
        }
    }
    (x0 != usize::MAX).then_some([x0 as f64, y0 as f64, x1 as f64, y1 as f64])
}

/// Decodes `path` and returns its pixels as `4 × res × res` bytes (channel-major, rows
/// top to bottom): RGB composited on white, then alpha (255 throughout for an image
/// without one).
pub fn load_image(path: &Path, res: usize) -> Result<Vec<u8>> {
    let rgba = decode_rgba(path)?;
    let (w, h) = (rgba.width() as usize, rgba.height() as usize);
    // Composite on white in the image's own (sRGB) values, as PIL-prepared data does.
    let side = w.min(h);
    let (x0, y0) = ((w - side) / 2, (h - side) / 2);
    let mut planes = vec![0f32; 4 * side * side];
    for y in 0..side {
        for x in 0..side {
            let p = rgba.get_pixel((x0 + x) as u32, (y0 + y) as u32).0;
            let a = p[3].clamp(0.0, 1.0);
            for c in 0..3 {
                planes[c * side * side + y * side + x] = p[c].clamp(0.0, 1.0) * a + (1.0 - a);
            }
            planes[3 * side * side + y * side + x] = a;
        }
    }
    let resized = area_resize(&planes, 4, side, res);
    Ok(resized.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).collect())
}

/// Decodes a PNG or JPEG file (grayscale, palette, 16-bit and alpha variants included) to
/// float RGBA. An unreadable, empty, unrecognised, truncated (JPEG) or zero-sized image is
/// an error naming the file and the reason.
pub fn decode_rgba(path: &Path) -> Result<image::Rgba32FImage> {
    let data_err = |reason: String| Error::Data { path: path.to_path_buf(), reason };
    let bytes = std::fs::read(path).map_err(|e| data_err(format!("cannot read the file: {e}")))?;
    if bytes.is_empty() {
        return Err(data_err("empty file (0 bytes)".into()));
    }
    let format =
        image::guess_format(&bytes).map_err(|_| data_err("not a PNG or JPEG file (unrecognised signature)".into()))?;
    if !matches!(format, image::ImageFormat::Png | image::ImageFormat::Jpeg) {
        return Err(data_err(format!("{format:?} images are not supported, expected PNG or JPEG")));
    }
    if format == image::ImageFormat::Jpeg && !jpeg_is_complete(&bytes) {
        // The JPEG decoder fills a truncated scan with grey instead of failing.
        return Err(data_err("truncated JPEG (no end-of-image marker after the image data)".into()));
    }
    // The header's size, read before decoding: a damaged or hostile header would otherwise
    // have the decoder allocate the image it claims (up to the decoder's 512 MiB limit).
    let reader = image::ImageReader::with_format(std::io::Cursor::new(&bytes), format);
    let (w, h) = reader.into_dimensions().map_err(|e| data_err(format!("cannot decode {format:?}: {e}")))?;
    let pixels = u64::from(w) * u64::from(h);
    if pixels > MAX_PIXELS_PER_BYTE * bytes.len() as u64 {
        return Err(data_err(format!(
            "its header claims {w}×{h} pixels, more than {} bytes of PNG or JPEG can hold \
             (at most {MAX_PIXELS_PER_BYTE} pixels a byte): the file is damaged",
            bytes.len()
        )));
    }
    let img = image::load_from_memory_with_format(&bytes, format)
        .map_err(|e| data_err(format!("cannot decode {format:?}: {e}")))?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    if w == 0 || h == 0 {
        return Err(data_err(format!("image has zero size ({w}×{h})")));
    }
    Ok(img.into_rgba32f())
}

/// The most pixels one byte of PNG can encode: deflate expands a byte into at most 1032,
/// each holding up to 8 pixels (1 bit a pixel). JPEG stays far below (≥ 1 bit a block of 64).
const MAX_PIXELS_PER_BYTE: u64 = 8 * 1032;

/// A JPEG is complete when an end-of-image marker (FF D9) follows its last
/// start-of-scan marker (FF DA); trailing bytes after it are allowed.
fn jpeg_is_complete(bytes: &[u8]) -> bool {
    let Some(sos) = bytes.windows(2).rposition(|w| w == [0xFF, 0xDA]) else {
        return false;
    };
    bytes[sos..].windows(2).any(|w| w == [0xFF, 0xD9])
}

/// Per output index, the input indices it overlaps and their area weights (summing to 1).
fn area_weights(src: usize, dst: usize) -> Vec<Vec<(usize, f32)>> {
    let scale = src as f64 / dst as f64;
    (0..dst)
        .map(|j| {
            let (lo, hi) = (j as f64 * scale, (j + 1) as f64 * scale);
            let first = lo.floor() as usize;
            let last = (hi.ceil() as usize).min(src);
            (first..last)
                .filter_map(|i| {
                    let overlap = (hi.min(i as f64 + 1.0) - lo.max(i as f64)).max(0.0);
                    (overlap > 0.0).then_some((i, (overlap / scale) as f32))
                })
                .collect()
        })
        .collect()
}

/// Resizes `channels` square planes of side `src` to side `dst` with the area filter
/// (upscaling repeats pixels, blending the two at fractional boundaries).
pub fn area_resize(planes: &[f32], channels: usize, src: usize, dst: usize) -> Vec<f32> {
    if src == dst {
        return planes.to_vec();
    }
    let wts = area_weights(src, dst);
    let mut out = vec![0f32; channels * dst * dst];
    let mut rows = vec![0f32; src * dst]; // horizontally resized plane: src rows × dst columns
    for c in 0..channels {
        let plane = &planes[c * src * src..(c + 1) * src * src];
        for y in 0..src {
            for (j, w) in wts.iter().enumerate() {
                rows[y * dst + j] = w.iter().map(|&(i, k)| plane[y * src + i] * k).sum();
            }
        }
        for (j, w) in wts.iter().enumerate() {
            for x in 0..dst {
                out[c * dst * dst + j * dst + x] = w.iter().map(|&(i, k)| rows[i * dst + x] * k).sum();
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn area_filter_averages_exactly() {
        // 4 → 2: each output is the mean of a 2×2 block.
        let plane: Vec<f32> = (0..16).map(|v| v as f32).collect();
        let out = area_resize(&plane, 1, 4, 2);
        assert_eq!(out, vec![2.5, 4.5, 10.5, 12.5]);
        // 3 → 2: fractional overlaps, still mean-preserving.
        let plane: Vec<f32> = (0..9).map(|v| (v * v) as f32).collect();
        let out = area_resize(&plane, 1, 3, 2);
        let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len() as f32;
        assert!((mean(&out) - mean(&plane)).abs() < 1e-4);
        for w in area_weights(7, 3) {
            assert!((w.iter().map(|x| x.1).sum::<f32>() - 1.0).abs() < 1e-6);
        }
    }

    #[test]
    fn jpeg_completeness() {
        assert!(jpeg_is_complete(&[0xFF, 0xD8, 0xFF, 0xDA, 1, 2, 0xFF, 0xD9]));
        assert!(jpeg_is_complete(&[0xFF, 0xD8, 0xFF, 0xDA, 1, 2, 0xFF, 0xD9, 0, 0]));
        assert!(!jpeg_is_complete(&[0xFF, 0xD8, 0xFF, 0xDA, 1, 2, 3]));
        assert!(!jpeg_is_complete(&[0xFF, 0xD8, 0xFF, 0xD9]));
    }
}
