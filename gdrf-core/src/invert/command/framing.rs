//! `gdrf-invert framing`: where the objects sit in a dataset's images, written beside a
//! generator as `framing.json` so that `gdrf-invert PHOTO` frames photos the same way.
use crate::data::{folder, Metadata, Split};
use crate::invert::framing::{Framing, FRAMING_PERCENTILES};
use crate::{progress, Error, Result};
use std::path::{Path, PathBuf};

/// The flags of `gdrf-invert framing`.
#[derive(clap::Args)]
pub struct FramingOptions {
    /// The training images: a procedural dataset (its training split, by metadata.json) or
    /// a folder of PNGs with alpha (every image in it, or in its images/ folder).
    #[arg(long, default_value = "data/chairs-64", value_name = "DIR")]
    pub dataset: PathBuf,
    /// The generator trained on them: framing.json is written beside it. Default: the
    /// shipped models/chairs-campaign.
    #[arg(long, visible_alias = "checkpoint", value_name = "FILE")]
    pub generator: Option<PathBuf>,
}

/// The training images of `dir` (see [`FramingOptions::dataset`]).
fn training_images(dir: &Path) -> Result<Vec<PathBuf>> {
    if dir.join(crate::data::METADATA_FILE).is_file() {
        let meta = Metadata::load(dir)?;
        return Ok(meta.images.iter().filter(|r| r.split == Split::Train).map(|r| dir.join(&r.file)).collect());
    }
    let images = dir.join("images");
    folder::list_images(if images.is_dir() { &images } else { dir })
}

/// Measures the framing of `--dataset` and writes it beside `--generator`.
pub fn framing(a: &FramingOptions) -> Result<()> {
    let gen = a.generator.clone().unwrap_or_else(crate::paths::shipped_generator);
    if !gen.is_file() {
        return Err(Error::Invalid(format!("--generator {}: no such file", gen.display())));
    }
    let files = training_images(&a.dataset)?;
    if files.is_empty() {
        return Err(Error::Invalid(format!("--dataset {}: no images", a.dataset.display())));
    }
    let bar = progress::bar(files.len() as u64, "images", false);
    bar.set_prefix("measuring");
    let mut planes = Vec::with_capacity(files.len());
    for f in &files {
        let rgba = folder::decode_rgba(f)?;
        if rgba.width() != rgba.height() {
            return Err(Error::Data { path: f.clone(), reason: "a training image must be square".into() });
        }
        planes.push((rgba.width() as usize, rgba.pixels().map(|p| p.0[3].clamp(0.0, 1.0)).collect::<Vec<f32>>()));
        bar.inc(1);
    }
    bar.finish_and_clear();
    if planes.iter().all(|(_, a)| a.iter().all(|&v| v >= 1.0)) {
        return Err(Error::Invalid(format!(
            "--dataset {}: its images have no alpha, so where their objects sit cannot be measured",
            a.dataset.display()
        )));
    }
    let f = Framing::measure(planes.iter().map(|(s, a)| (*s, a.as_slice())), &crate::paths::shown(&a.dataset))?;
    let out = Framing::file_beside(&gen);
    let text = serde_json::to_string_pretty(&f).map_err(|e| Error::Invalid(e.to_string()))?;
    crate::paths::write_atomic(&out, (text + "\n").as_bytes())?;
    println!(
        "{} images: the object's longer side {:.3}–{:.3} of the image, its centre at x {:.3}–{:.3}, y {:.3}–{:.3} (percentiles {}–{}); wrote {}",
        f.images,
        f.size[0],
        f.size[1],
        f.centre_x[0],
        f.centre_x[1],
        f.centre_y[0],
        f.centre_y[1],
        FRAMING_PERCENTILES[0],
        FRAMING_PERCENTILES[1],
        out.display()
    );
    Ok(())
}
