//! The scaled-patch step (`[stages.patch]`) in the training loop, on a tiny model: what the
//! discriminator is shown of the real images, the patches' sharing and annealing, and a run
//! that switches from whole images to scaled patches by `--resume --config`, continuing
//! exactly across the switch and after a resume.
mod common;

use common::{assert_close, copy_dir, params, run_steps, same_params, TempDir};
use gdrf_core::camera::patch::{real_patches, Patch};
use gdrf_core::train::{PatchConfig, TrainConfig, Trainer};
use gdrf_core::Background;
use std::path::Path;

/// A tiny model on 16 procedural chairs at 16²: 8² whole images for `switch` steps (none
/// when 0), then 16² images, whole or (with `patch`) in 8² scaled patches. The campaign's step: one
/// render, corner backgrounds, minibatch-std groups and mode-seeking pairs.
fn config(dir: &Path, switch: i64, patch: Option<PatchConfig>) -> TrainConfig {
    let whole8 = if switch == 0 {
        String::new()
    } else {
        "[[stages]]\nfrom_step = 0\nresolution = 8\nnum_steps = 4\nbatch_size = 4\n".to_string()
    };
    let rest = format!(
        r#"
[samples]
count = 2
swap = 2
yaws = [0.0, 1.0]

[loss]
diversity_weight = 1.0

{whole8}
[[stages]]
from_step = {switch}
resolution = 16
num_steps = 4
batch_size = 4

[data]
path = "{data}"

[data.synth]
count = 16
resolution = 16
supersample = 1
shadows = false
"#,
        data = dir.join("data").display()
    );
    let schedule = "total_steps = 100\nfade_steps = 2\nlog_interval = 1\ncheckpoint_interval = 100\nkeep_checkpoints = 2\nsample_interval = 100";
    let text = common::tiny_training_toml("seed = 3\nstep = \"one-render\"", schedule, &rest);
    let mut cfg = TrainConfig::from_toml(&text, Path::new("")).unwrap();
    cfg.generator.background = Background::Corners;
    cfg.discriminator.minibatch_std_group = 2;
    cfg.stages.last_mut().unwrap().patch = patch;
    cfg.validate().unwrap();
    cfg
}

fn patch(beta_start: f64, beta_end: f64, anneal_images: i64) -> Option<PatchConfig> {
    Some(PatchConfig { size: 8, beta_start, beta_end, anneal_images, native_share: 0.0 })
}

/// The discriminator is shown the real images resampled at the step's patches: at β → 0
/// every patch is the whole image, which is then the image the 8² stage would show (the
/// dataset cache's area filter); at β = 1 the patches of the 16² images, which the
/// minibatch-std groups and the mode-seeking pairs of the campaign's batch share.
#[test]
fn the_discriminator_sees_the_real_images_at_the_steps_patches() {
    let dir = TempDir::new("scaled-patch-reals").unwrap();
    let mut whole8 = Trainer::new(config(&dir.0, 100, None), &dir.path("whole8")).unwrap();
    whole8.prepare_data(&|_| {}).unwrap();
    let want = whole8.judged_real_now().unwrap();
    assert_eq!(want.size(), [4, 3, 8, 8]);

    let mut whole = Trainer::new(config(&dir.0, 0, None), &dir.path("whole16")).unwrap();
    assert!(whole.patches_now().is_none());
    let real16 = whole.judged_real_now().unwrap();
    assert_eq!(real16.size(), [4, 3, 16, 16]);

    let mut tiny = Trainer::new(config(&dir.0, 0, patch(1e-9, 1e-9, 0)), &dir.path("tiny")).unwrap();
    let patches = tiny.patches_now().unwrap();
    assert!(patches.iter().all(|p| *p == Patch::whole()), "{patches:?}");
    // The same area filter over the same composited pixels, but the caches hold bytes: the
    // 8² cache rounds its mean once, the patch averages the 16² cache's rounded bytes. Each
    // rounding is within half a level, so the two differ by at most one level, 2/255 in
    // the discriminator's [−1, 1]. (In floats the filters are equal: camera::patch's tests.)
    assert_close("whole-image patches", &tiny.judged_real_now().unwrap(), &want, 2.0 / 255.0 + 1e-6, 0.0);

    let mut placed = Trainer::new(config(&dir.0, 0, patch(1.0, 1.0, 0)), &dir.path("placed")).unwrap();
    let patches = placed.patches_now().unwrap();
    // Groups of 2 in 4 (images i, i + 2) and pairs (0, 1), (2, 3): one patch for the batch.
    assert!(patches.iter().all(|p| *p == patches[0]), "{patches:?}");
    let p = patches[0];
    assert!(p.scale > 0.5 && p.scale < 1.0, "{p:?}");
    p.check(8, 16).unwrap();
    let got = placed.judged_real_now().unwrap();
    assert_eq!(got.size(), [4, 3, 8, 8]);
    assert!(got.equal(&real_patches(&real16, &patches, 8).unwrap()));
    // Each step its own patches.
    run_steps(&mut placed, 1);
    assert_ne!(placed.patches_now().unwrap()[0], p);
}

/// A run trained on whole 8² images switches by `--resume --config` to 8² patches of 16²
/// images: the discriminator's input stays 8², so nothing fades in; the scales anneal from
/// whole images; the losses stay finite; and a copy resumed after the switch continues the
/// very same numbers.
#[test]
fn a_run_switches_to_scaled_patches_and_resumes_exactly() {
    let dir = TempDir::new("scaled-patch-switch").unwrap();
    let before = config(&dir.0, 100, None);
    let mut t = Trainer::new(before.clone(), &dir.path("a")).unwrap();
    t.prepare_data(&|_| {}).unwrap();
    run_steps(&mut t, 2);
    drop(t);
    copy_dir(&dir.path("a"), &dir.path("b"));
    // β from 0.001 to 1 over 16 images (4 steps of 4).
    let after = config(&dir.0, 2, patch(0.001, 1.0, 16));

    let mut a = Trainer::resume_with(&dir.path("a"), after.clone()).unwrap();
    assert_eq!(a.patches_now().unwrap()[0], Patch::whole(), "β = 0.001: whole images first");
    let full = run_steps(&mut a, 6);
    for r in &full {
        assert_eq!((r.resolution, r.alpha), (16, 1.0), "step {}", r.step);
        assert!(r.d_total.is_finite() && r.g_total.is_finite(), "step {}", r.step);
        assert!(!r.d_skipped && !r.g_skipped);
    }
    // Annealed: by step 6 (16 images in) β = 1, and the scales are drawn below 1.
    assert!(a.patches_now().unwrap()[0].scale < 1.0);

    let mut b = Trainer::resume_with(&dir.path("b"), after).unwrap();
    run_steps(&mut b, 3);
    drop(b);
    let mut b = Trainer::resume(&dir.path("b"), None).unwrap();
    assert_eq!(b.progress().step, 5);
    let rest = run_steps(&mut b, 3);
    for (x, y) in full[3..].iter().zip(&rest) {
        assert_eq!(x.step, y.step);
        assert_eq!(x.d_total.to_bits(), y.d_total.to_bits(), "step {}: D {} vs {}", x.step, x.d_total, y.d_total);
        assert_eq!(x.g_total.to_bits(), y.g_total.to_bits(), "step {}: G {} vs {}", x.step, x.g_total, y.g_total);
        assert_eq!(x.g_terms, y.g_terms);
    }
    assert!(same_params(&params(a.generator_vars()), &params(b.generator_vars())));
    assert!(same_params(&params(a.disc_vars()), &params(b.disc_vars())));
}

/// `loss.pose_min_scale` in the loop: with the bound at 1, a step whose patch is smaller than
/// the image trains no pose term (D's on reals and fakes, G's are all exactly 0), while the
/// same step without the bound trains them all; the adversarial terms are the same step's.
#[test]
fn the_pose_terms_skip_patches_below_the_bound() {
    let dir = TempDir::new("scaled-patch-pose").unwrap();
    let term = |r: &gdrf_core::train::StepReport, k: &str| {
        r.d_terms.iter().chain(&r.g_terms).find(|(n, _)| *n == k).map(|(_, v)| *v).unwrap()
    };
    let mut reports = Vec::new();
    for (name, bound) in [("every", 0.0), ("whole", 1.0)] {
        let mut cfg = config(&dir.0, 0, patch(1.0, 1.0, 0));
        cfg.loss.pose_min_scale = bound;
        let mut t = Trainer::new(cfg, &dir.path(name)).unwrap();
        t.prepare_data(&|_| {}).unwrap();
        assert!(t.patches_now().unwrap()[0].scale < 1.0);
        reports.push(run_steps(&mut t, 1).remove(0));
    }
    for k in ["d_pose_real", "d_pose_fake", "g_pose"] {
        assert!(term(&reports[0], k) > 0.0, "{k} without the bound");
        assert_eq!(term(&reports[1], k), 0.0, "{k} under the bound");
    }
    assert_eq!(term(&reports[0], "d_real").to_bits(), term(&reports[1], "d_real").to_bits());
}

/// Bad `[stages.patch]` settings are errors that name the key.
#[test]
fn bad_patch_settings_are_named() {
    let dir = TempDir::new("scaled-patch-config").unwrap();
    let mut cfg = config(&dir.0, 2, None);
    for (p, key) in [
        (PatchConfig { size: 32, ..Default::default() }, "stages[1].patch.size is 32"),
        (PatchConfig { size: 12, ..Default::default() }, "stages[1].patch.size is 12"),
        (PatchConfig { size: 8, beta_start: 0.0, ..Default::default() }, "stages[1].patch.beta_start is 0"),
        (PatchConfig { size: 8, beta_end: f64::NAN, ..Default::default() }, "stages[1].patch.beta_end"),
        (PatchConfig { size: 8, anneal_images: -1, ..Default::default() }, "stages[1].patch.anneal_images is -1"),
        (PatchConfig { size: 8, native_share: 1.0, ..Default::default() }, "stages[1].patch.native_share is 1"),
        (PatchConfig { size: 8, native_share: -0.1, ..Default::default() }, "stages[1].patch.native_share is -0.1"),
    ] {
        cfg.stages[1].patch = Some(p);
        let e = cfg.validate().unwrap_err().to_string();
        assert!(e.contains(key), "{e}");
    }
    // A native share is written where set and only there, so that the configs stored with
    // earlier runs write back unchanged.
    cfg.stages[1].patch = patch(0.1, 0.8, 10);
    cfg.validate().unwrap();
    assert!(!cfg.to_toml().unwrap().contains("native_share"));
    cfg.stages[1].patch.as_mut().unwrap().native_share = 0.25;
    cfg.validate().unwrap();
    let text = cfg.to_toml().unwrap();
    assert!(text.contains("native_share = 0.25"), "{text}");
    let back = TrainConfig::from_toml(&text, &dir.0).unwrap();
    assert_eq!(back.stages[1].patch.as_ref().unwrap().native_share, 0.25);
    cfg.discriminator.kind = gdrf_core::disc::DiscKind::Projected;
    let e = cfg.validate().unwrap_err().to_string();
    assert!(e.contains("stages[1].patch") && e.contains("\"projected\""), "{e}");
}
