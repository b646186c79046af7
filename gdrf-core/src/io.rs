//! Image operations: tensors to PNG files (written atomically), grids, and resizing.
use crate::paths::write_atomic;
use crate::{Error, Result};
use std::path::Path;
use tch::{Kind, Tensor};

/// Converts `(3, H, W)` in [−1, 1] (or `(1, H, W)` in [0, 1] with `unit_range`) to 8-bit RGB.
pub fn to_rgb8(img: &Tensor, unit_range: bool) -> Result<image::RgbImage> {
    let img = img.detach().to_device(tch::Device::Cpu).to_kind(Kind::Float);
    let (c, h, w) = match img.size()[..] {
        [c, h, w] if c == 1 || c == 3 => (c, h, w),
        ref s => return Err(Error::Shape(format!("expected a (3|1, H, W) image, got shape {s:?}"))),
    };
    let img = if unit_range { img } else { (img + 1.0) * 0.5 };
    let img = img.nan_to_num(0.0, 1.0, 0.0).clamp(0.0, 1.0) * 255.0;
    let img = img.round().to_kind(Kind::Uint8).expand([3, h, w], false).permute([1, 2, 0]).contiguous();
    let _ = c;
    let data = Vec::<u8>::try_from(img.view([-1]))?;
    image::RgbImage::from_raw(w as u32, h as u32, data)
        .ok_or_else(|| Error::Invalid("image buffer size mismatch".into()))
}

/// Tiles `(B, 3, H, W)` images in [−1, 1] into a grid with `cols` columns.
pub fn grid(images: &Tensor, cols: i64) -> Tensor {
    let s = images.size();
    let (b, c, h, w) = (s[0], s[1], s[2], s[3]);
    let cols = cols.clamp(1, b.max(1));
    let rows = (b + cols - 1) / cols;
    let pad = rows * cols - b;
    let imgs = if pad > 0 {
        Tensor::cat(&[images.shallow_clone(), images.narrow(0, 0, 1).ones_like().expand([pad, c, h, w], false)], 0)
    } else {
        images.shallow_clone()
    };
    imgs.view([rows, cols, c, h, w]).permute([2, 0, 3, 1, 4]).reshape([c, rows * h, cols * w])
}

/// Writes an 8-bit RGB image as PNG, atomically.
/// An output folder to write into (`flag` names the option): created when missing; one
/// that already holds files is refused unless `force`, so that no earlier output is mixed
/// with or overwritten by a new one by accident.
pub fn output_dir(dir: &Path, force: bool, flag: &str) -> Result<()> {
    let io = |source| Error::Io { path: dir.to_path_buf(), err: source };
    if dir.is_dir() && std::fs::read_dir(dir).map_err(io)?.next().is_some() && !force {
        return Err(Error::Invalid(format!(
            "{flag} {}: the folder already holds files; pass --force to write into it",
            dir.display()
        )));
    }
    std::fs::create_dir_all(dir).map_err(io)
}

pub fn save_png(path: &Path, img: &image::RgbImage) -> Result<()> {
    let bytes = png_bytes(img).map_err(|e| Error::Invalid(format!("{}: {e}", path.display())))?;
    write_atomic(path, &bytes)
}

/// An 8-bit RGB image encoded as PNG, in memory.
pub fn png_bytes(img: &image::RgbImage) -> Result<Vec<u8>> {
    let mut bytes = Vec::new();
    image::DynamicImage::ImageRgb8(img.clone())
        .write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)
        .map_err(|e| Error::Invalid(format!("PNG encoding failed: {e}")))?;
    Ok(bytes)
}

/// Maps `values: (1, H, W)` in [0, 1] (clamped; NaN → 0) through viridis to an image
/// `(3, H, W)` in [−1, 1], for depth and opacity maps.
pub fn colour_map(values: &Tensor) -> Tensor {
    // Viridis at 0, ¼, ½, ¾, 1, linearly interpolated.
    const STOPS: [[f64; 3]; 5] = [
        [0.267, 0.005, 0.329],
        [0.229, 0.322, 0.546],
        [0.128, 0.567, 0.551],
        [0.369, 0.789, 0.383],
        [0.993, 0.906, 0.144],
    ];
    let v = values.nan_to_num(0.0, 1.0, 0.0).clamp(0.0, 1.0) * 4.0;
    let idx = v.floor().clamp(0.0, 3.0);
    let frac = &v - &idx;
    let stops = Tensor::from_slice(&STOPS.concat()).view([5, 3]).to_kind(values.kind()).to_device(values.device());
    let i = idx.to_kind(Kind::Int64).view([-1]);
    let lo = stops.index_select(0, &i);
    let hi = stops.index_select(0, &(&i + 1));
    let f = frac.view([-1, 1]);
    let rgb = &lo + (hi - &lo) * f;
    let (h, w) = (values.size()[1], values.size()[2]);
    rgb.transpose(0, 1).reshape([3, h, w]) * 2.0 - 1.0
}

/// Depth maps `(B, 1, H, W)` (or `(1, H, W)`) through viridis, near (`near`, dark) to far
/// (`far`, yellow), as images in [−1, 1] with three channels: the one depth picture of every
/// command.
pub fn depth_map(depth: &Tensor, near: f64, far: f64) -> Tensor {
    let d = (depth - near) / (far - near);
    if d.dim() == 3 {
        return colour_map(&d);
    }
    Tensor::stack(&(0..d.size()[0]).map(|i| colour_map(&d.get(i))).collect::<Vec<_>>(), 0)
}

/// Writes frames as an endlessly looping animated GIF (`delay_ms` per frame), atomically.
pub fn save_gif(path: &Path, frames: &[image::RgbImage], delay_ms: u32) -> Result<()> {
    let bytes = gif_bytes(frames, delay_ms).map_err(|e| Error::Invalid(format!("{}: {e}", path.display())))?;
    write_atomic(path, &bytes)
}

/// Frames encoded as an endlessly looping animated GIF (`delay_ms` per frame), in memory.
pub fn gif_bytes(frames: &[image::RgbImage], delay_ms: u32) -> Result<Vec<u8>> {
    use image::codecs::gif::{GifEncoder, Repeat};
    let fail = |e: image::ImageError| Error::Invalid(format!("GIF encoding failed: {e}"));
    let mut bytes = Vec::new();
    {
        let mut enc = GifEncoder::new_with_speed(&mut bytes, 10);
        enc.set_repeat(Repeat::Infinite).map_err(fail)?;
        let delay = image::Delay::from_numer_denom_ms(delay_ms, 1);
        for f in frames {
            let rgba = image::DynamicImage::ImageRgb8(f.clone()).to_rgba8();
            enc.encode_frame(image::Frame::from_parts(rgba, 0, 0, delay)).map_err(fail)?;
        }
    }
    Ok(bytes)
}

/// `(B, 3, H, W)` → `(B, 3, res, res)`: antialiased bilinear when shrinking.
pub fn resize(img: &Tensor, res: i64) -> Tensor {
    let s = img.size();
    if s[2] == res && s[3] == res {
        return img.shallow_clone();
    }
    if s[2] > res {
        img.internal_upsample_bilinear2d_aa([res, res], false, None, None)
    } else {
        img.upsample_bilinear2d([res, res], false, None, None)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_maps_run_from_near_dark_to_far_yellow() {
        let d = Tensor::from_slice(&[0.5f32, 1.5, 9.0]).view([1, 1, 1, 3]);
        let m = depth_map(&d, 0.5, 1.5);
        assert_eq!(m.size(), [1, 3, 1, 3]);
        let px = |i: i64| Vec::<f32>::try_from((m.get(0).select(1, 0).select(1, i) + 1.0) / 2.0).unwrap();
        let close = |a: Vec<f32>, b: [f32; 3]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-6);
        assert!(close(px(0), [0.267, 0.005, 0.329]), "near: viridis' first stop");
        assert!(close(px(1), [0.993, 0.906, 0.144]), "far: its last");
        assert!(close(px(2), [0.993, 0.906, 0.144]), "beyond far: clamped");
        assert_eq!(depth_map(&d.get(0), 0.5, 1.5).size(), [3, 1, 3]);
    }

    #[test]
    fn occupied_output_folders_need_force() {
        let dir = std::env::temp_dir().join(format!("gdrf-io-out-{}", std::process::id()));
        output_dir(&dir, false, "--out").unwrap();
        assert!(dir.is_dir());
        output_dir(&dir, false, "--out").unwrap(); // empty: fine
        std::fs::write(dir.join("frame-000.png"), b"x").unwrap();
        let e = output_dir(&dir, false, "--out").unwrap_err().to_string();
        assert!(e.contains("--out") && e.contains("--force") && e.contains(&dir.display().to_string()), "{e}");
        output_dir(&dir, true, "--out").unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
    }
    use image::AnimationDecoder;

    #[test]
    fn the_colour_map_runs_from_dark_violet_to_yellow() {
        let v = Tensor::from_slice(&[0.0f64, 0.5, 1.0, f64::NAN, 7.0]).view([1, 1, 5]);
        let c = (colour_map(&v) + 1.0) * 0.5;
        let px = |i: i64| Vec::<f64>::try_from(c.select(2, i).view([-1])).unwrap();
        assert!((px(0)[0] - 0.267).abs() < 1e-9 && (px(0)[2] - 0.329).abs() < 1e-9);
        assert!((px(1)[1] - 0.567).abs() < 1e-9);
        assert!((px(2)[0] - 0.993).abs() < 1e-9 && (px(2)[2] - 0.144).abs() < 1e-9);
        assert_eq!(px(3), px(0));
        assert_eq!(px(4), px(2));
    }

    #[test]
    fn gifs_hold_every_frame() {
        let frames: Vec<image::RgbImage> =
            (0..3u8).map(|i| image::RgbImage::from_pixel(6, 4, image::Rgb([80 * i, 0, 255 - 80 * i]))).collect();
        let path = std::env::temp_dir().join(format!("gdrf-io-{}.gif", std::process::id()));
        save_gif(&path, &frames, 100).unwrap();
        let dec =
            image::codecs::gif::GifDecoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap())).unwrap();
        let back = dec.into_frames().collect_frames().unwrap();
        assert_eq!(back.len(), 3);
        assert_eq!(back[2].buffer().dimensions(), (6, 4));
        // Pure red, green and blue mixes survive the palette to within its rounding.
        let p = back[2].buffer().get_pixel(0, 0);
        assert!((p[0] as i32 - 160).abs() <= 8 && (p[2] as i32 - 95).abs() <= 8, "{p:?}");
        std::fs::remove_file(&path).unwrap();
    }
}
