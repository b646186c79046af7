//! scripts/white_density.py, the campaign's diagnostic of density painted the background's
//! white (docs/campaign-log.md, "Why structure falls short: density painted white"): its counts on an image whose answer is known, and on the
//! shipped generator at thresholds that make every opaque pixel white, or none.
mod common;

use common::{python, repo_root, TempDir};
use serde_json::Value;
use std::process::Command;

/// Runs the script; returns its JSON lines.
fn white_density(args: &[&str]) -> Vec<Value> {
    let out = Command::new(python())
        .arg(repo_root().join("scripts/white_density.py"))
        .args(args)
        .output()
        .expect("failed to start python");
    assert!(out.status.success(), "white_density.py {args:?} failed:\n{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

fn number(v: &Value, key: &str) -> f64 {
    v[key].as_f64().unwrap_or_else(|| panic!("no number {key} in {v}"))
}

#[test]
fn white_density_counts_what_it_says() {
    let tmp = TempDir::new("white-density").unwrap();
    // An 8×8 "dataset" image (the render resolution below, so it is not resampled): 32 opaque
    // white pixels, 16 opaque red ones, 8 transparent and 8 black at alpha 0.4 (fog 0.2).
    std::fs::create_dir_all(tmp.path("data/images")).unwrap();
    let img = image::RgbaImage::from_fn(8, 8, |_, y| match y {
        0..=3 => image::Rgba([255, 255, 255, 255]),
        4 | 5 => image::Rgba([200, 0, 0, 255]),
        6 => image::Rgba([0, 0, 0, 0]),
        _ => image::Rgba([0, 0, 0, 102]),
    });
    img.save(tmp.path("data/images/000000.png")).unwrap();
    let shipped = repo_root().join("models/chairs-campaign/generator.safetensors");
    let figure = tmp.path("figure.png");
    let common = ["--codes", "2", "--resolution", "8", "--samples", "4"];
    let run = |threshold: &str, extra: &[&str]| {
        let mut args = vec![shipped.to_str().unwrap(), "--threshold", threshold];
        args.extend(common);
        args.extend(extra);
        white_density(&args)
    };
    let data = tmp.path("data");
    let lines = run("0.9", &["--dataset", data.to_str().unwrap(), "--figure", figure.to_str().unwrap()]);
    assert_eq!(lines.len(), 2, "{lines:?}");
    let (real, model) = (&lines[0], &lines[1]);
    assert_eq!(number(real, "images"), 1.0);
    assert!((number(real, "opaque_area") - 48.0 / 64.0).abs() < 1e-12, "{real}");
    assert!((number(real, "white_of_opaque") - 32.0 / 48.0).abs() < 1e-12, "{real}");
    assert!((number(real, "fog") - 0.2).abs() < 1e-6, "{real}");
    // The black pixels at alpha 0.4 show as 0.6 on white (tint 0.4), the transparent ones as
    // white (tint 0).
    assert!((number(real, "tint") - 0.2).abs() < 1e-6, "{real}");
    assert_eq!(number(model, "codes"), 2.0);
    let area = number(model, "opaque_area");
    for key in ["opaque_area", "white_of_opaque", "white_flips_under_swap"] {
        let v = number(model, key);
        assert!((0.0..=1.0).contains(&v), "{key} = {v}");
    }
    let fog = number(model, "fog");
    assert!((0.0..=0.5).contains(&fog), "fog = {fog}: the mean opacity of pixels at most half opaque");
    let tint = number(model, "tint");
    assert!((0.0..=1.0).contains(&tint), "tint = {tint}");
    // 2 codes at 64², enlarged twice: renders above, opacity below.
    assert_eq!(image::image_dimensions(&figure).unwrap(), (2 * 64 * 2, 2 * 64 * 2));
    // Every channel lies below 1.1 and above −0.1: no opaque pixel is white, or all are, and
    // none flips under a swap; the opaque area does not depend on the threshold.
    for (threshold, white) in [("1.1", 0.0), ("-0.1", 1.0)] {
        let m = &run(threshold, &[])[0];
        assert_eq!(number(m, "opaque_area"), area, "{m}");
        assert!(area > 0.0, "the shipped model draws nothing opaque: {m}");
        assert_eq!(number(m, "white_of_opaque"), white, "{m}");
        assert_eq!(number(m, "white_flips_under_swap"), 0.0, "{m}");
    }
}
