//! Image output: tensors to PNG files, written atomically.
use crate::checkpoint::write_atomic;
use crate::{Error, Result};
use std::path::Path;
use tch::{Kind, Tensor};

/// Converts `(3, H, W)` in [−1, 1] (or `(1, H, W)` in [0, 1] with `unit_range`) to 8-bit RGB.
pub fn to_rgb8(img: &Tensor, unit_range: bool) -> Result<image::RgbImage> {
    let img = img.detach().to_device(tch::Device::Cpu).to_kind(Kind::Float);
    let (c, h, w) = match img.size()[..] {
        [c, h, w] if c == 1 || c == 3 => (c, h, w),
        ref s => return Err(Error::Invalid(format!("expected a (3|1, H, W) image, got shape {s:?}"))),
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
pub fn save_png(path: &Path, img: &image::RgbImage) -> Result<()> {
    let mut bytes = Vec::new();
    image::DynamicImage::ImageRgb8(img.clone())
        .write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)
        .map_err(|e| Error::Invalid(format!("{}: PNG encoding failed: {e}", path.display())))?;
    write_atomic(path, &bytes)
}
