//! The training loop on a tiny model (seconds on a CPU): checkpoints and exports, exact
//! resume, the non-finite guard (skip, then rollback), fade-in, stage switches and EMA at
//! their configured steps, refusal of non-finite checkpoints, resuming past a damaged
//! newest checkpoint, and the two-pass patch step giving the single-pass gradient.
mod common;

use common::{copy_dir, params, run_steps, same_params, TempDir};
use gdrf_core::checkpoint::load_generator;
use gdrf_core::disc::augment::Augmentation;
use gdrf_core::disc::DiscKind;
use gdrf_core::loss::gan::Adversarial;
use gdrf_core::loss::LossConfig;
use gdrf_core::train::{run, RunLimits, StepReport, Stopped, TrainConfig, Trainer};
use gdrf_core::Background;
use std::path::Path;
use std::sync::atomic::AtomicBool;
use tch::{Device, Kind, Tensor};

/// A tiny model on 16 procedural chairs at 16², rendered at 8² then 16².
fn tiny_config(dir: &Path, extra: &str) -> TrainConfig {
    let rest = format!(
        r#"
[samples]
count = 2
swap = 2
yaws = [0.0, 1.0]

[[stages]]
from_step = 0
resolution = 8
num_steps = 4
batch_size = 2

[[stages]]
from_step = 3
resolution = 16
num_steps = 4
batch_size = 2
g_lr = 3e-4

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
    let schedule = "total_steps = 100\nfade_steps = 2\nlog_interval = 1\ncheckpoint_interval = 2\nkeep_checkpoints = 2\nsample_interval = 4";
    let text = common::tiny_training_toml(&format!("seed = 5\n{extra}"), schedule, &rest);
    TrainConfig::from_toml(&text, Path::new("")).unwrap()
}

fn never() -> AtomicBool {
    AtomicBool::new(false)
}

#[test]
fn a_few_steps_write_checkpoints_metrics_previews_and_an_ema_export() {
    let dir = TempDir::new("train-few").unwrap();
    let cfg = tiny_config(&dir.0, "");
    let mut t = Trainer::new(cfg.clone(), &dir.path("run")).unwrap();
    t.prepare_data(&|_| {}).unwrap();
    let reports = run_steps(&mut t, 5);
    assert_eq!(reports.len(), 5);
    assert_eq!(t.progress().step, 5);
    let run_dir = dir.path("run");
    // Checkpoints at 2 and 4 (interval 2) and the final one at 5; only the newest 2 kept.
    let ckpts: Vec<i64> = run::list_checkpoints(&run_dir).unwrap().iter().map(|c| c.0).collect();
    assert_eq!(ckpts, [4, 5]);
    assert_eq!(TrainConfig::load(&run_dir.join(run::CONFIG)).unwrap().stages, cfg.stages);
    let metrics = run::read_metrics(&run_dir).unwrap();
    assert_eq!(metrics.iter().map(|m| m["step"].as_i64().unwrap()).collect::<Vec<_>>(), [0, 1, 2, 3, 4]);
    for key in ["d_real", "d_fake", "d_r1", "d_pose_fake", "d_pose_real"] {
        assert!(metrics[0]["d"][key].as_f64().unwrap().is_finite(), "{key}");
    }
    for key in ["g_adv", "g_pose", "reg_correction", "reg_smoothness", "reg_rigidity", "reg_normal"] {
        assert!(metrics[0]["g"][key].as_f64().unwrap().is_finite(), "{key}");
    }
    assert!(metrics[0]["grad_norm_g"].as_f64().unwrap() > 0.0);
    // Previews at 0 and 4, plus the final ones at 5.
    for tag in ["step-00000000", "step-00000004", "step-00000005"] {
        for kind in ["samples", "swap", "template"] {
            let p = run_dir.join(run::SAMPLES).join(format!("{tag}-{kind}.png"));
            assert!(p.is_file(), "{}", p.display());
        }
    }
    let swap = image::open(run_dir.join(run::SAMPLES).join("latest-swap.png")).unwrap();
    assert_eq!((swap.width(), swap.height()), (32, 32)); // 2 × 2 at the 16² stage
                                                         // The export and the training checkpoint both load as the EMA generator.
    let exported = load_generator(&run_dir.join(run::GENERATOR), Device::Cpu, Kind::Float).unwrap();
    let from_ckpt = load_generator(&run::latest_checkpoint(&run_dir).unwrap().1, Device::Cpu, Kind::Float).unwrap();
    assert!(same_params(&params(&exported.vs), &params(t.ema_vars())));
    assert!(same_params(&params(&from_ckpt.vs), &params(t.ema_vars())));
    assert!(!same_params(&params(t.ema_vars()), &params(t.generator_vars())), "the EMA differs from the live weights");
}

#[test]
fn a_resumed_run_reproduces_the_uninterrupted_run_exactly() {
    let dir = TempDir::new("train-resume").unwrap();
    let mut cfg = tiny_config(&dir.0, "");
    cfg.schedule.checkpoint_interval = 100;
    let mut a = Trainer::new(cfg.clone(), &dir.path("a")).unwrap();
    a.prepare_data(&|_| {}).unwrap();
    let full = run_steps(&mut a, 6);

    let mut b = Trainer::new(cfg, &dir.path("b")).unwrap();
    run_steps(&mut b, 4); // stops with a checkpoint after step index 3 (inside stage 2)
    drop(b);
    let mut b = Trainer::resume(&dir.path("b"), None).unwrap();
    assert_eq!(b.progress().step, 4);
    let rest = run_steps(&mut b, 2);
    for (x, y) in full[4..].iter().zip(&rest) {
        assert_eq!(x.step, y.step);
        assert_eq!(x.d_total.to_bits(), y.d_total.to_bits(), "step {}: D {} vs {}", x.step, x.d_total, y.d_total);
        assert_eq!(x.g_total.to_bits(), y.g_total.to_bits(), "step {}: G {} vs {}", x.step, x.g_total, y.g_total);
        assert_eq!(x.g_terms, y.g_terms);
        assert_eq!(x.grad_norm_g.to_bits(), y.grad_norm_g.to_bits());
    }
    assert!(same_params(&params(a.generator_vars()), &params(b.generator_vars())));
    assert!(same_params(&params(a.ema_vars()), &params(b.ema_vars())));
    assert!(same_params(&params(a.disc_vars()), &params(b.disc_vars())));
    // The resumed run's metrics hold each step once.
    let steps: Vec<i64> =
        run::read_metrics(&dir.path("b")).unwrap().iter().map(|m| m["step"].as_i64().unwrap()).collect();
    assert_eq!(steps, [0, 1, 2, 3, 4, 5]);
}

#[test]
fn the_projected_discriminator_with_hinge_loss_augmentation_and_the_coverage_term_trains_and_resumes_exactly() {
    let dir = TempDir::new("train-projected").unwrap();
    let mut cfg = tiny_config(&dir.0, "");
    cfg.schedule.checkpoint_interval = 100;
    cfg.discriminator.kind = DiscKind::Projected;
    cfg.discriminator.augment = vec![Augmentation::Color, Augmentation::Translation, Augmentation::Cutout];
    cfg.loss.adversarial = Adversarial::Hinge;
    cfg.loss.r1_gamma = 0.0;
    cfg.loss.coverage_weight = 1.0;
    cfg.loss.coverage_candidates = 3;
    cfg.loss.coverage_resolution = 4;
    let mut a = Trainer::new(cfg.clone(), &dir.path("a")).unwrap();
    a.prepare_data(&|_| {}).unwrap();
    let full = run_steps(&mut a, 4);
    for r in &full {
        let cov = r.g_terms.iter().find(|(k, _)| *k == "g_coverage").expect("a coverage term").1;
        assert!(cov.is_finite() && cov > 0.0, "step {}: coverage {cov}", r.step);
        assert!(r.grad_norm_d > 0.0 && r.grad_norm_g > 0.0);
        // Hinge terms are means of relu(1 ∓ logit): never negative.
        for k in ["d_real", "d_fake"] {
            let v = r.d_terms.iter().find(|(n, _)| *n == k).expect(k).1;
            assert!(v.is_finite() && v >= 0.0, "step {}: {k} {v}", r.step);
        }
    }
    // The augmentation reaches both players: without it, the same seed's first step gives
    // another D loss and other G terms.
    let mut plain = cfg.clone();
    plain.discriminator.augment.clear();
    let mut c = Trainer::new(plain, &dir.path("c")).unwrap();
    let first = run_steps(&mut c, 1).remove(0);
    assert_ne!(first.d_total, full[0].d_total);
    let adv = |r: &StepReport| r.g_terms.iter().find(|(k, _)| *k == "g_adv").expect("g_adv").1;
    assert_ne!(adv(&first), adv(&full[0]));
    // The spectral norm's power-iteration vectors and the fixed projections are saved with
    // D, so a resumed run continues the very same numbers.
    let mut b = Trainer::new(cfg, &dir.path("b")).unwrap();
    run_steps(&mut b, 2);
    drop(b);
    let mut b = Trainer::resume(&dir.path("b"), None).unwrap();
    let rest = run_steps(&mut b, 2);
    for (x, y) in full[2..].iter().zip(&rest) {
        assert_eq!(x.d_total.to_bits(), y.d_total.to_bits(), "step {}: D {} vs {}", x.step, x.d_total, y.d_total);
        assert_eq!(x.g_terms, y.g_terms, "step {}", x.step);
    }
    assert!(same_params(&params(a.disc_vars()), &params(b.disc_vars())));
    assert!(same_params(&params(a.generator_vars()), &params(b.generator_vars())));
    // The exported generator says which discriminator shaped it, and the evaluation reads it.
    let g = load_generator(&dir.path("a").join("generator.safetensors"), Device::Cpu, Kind::Float).unwrap();
    assert_eq!(g.header.info.get("discriminator").map(String::as_str), Some("projected"));
    // … and the resolution and samples per ray of its last step (stage 2 from step 3: 16², 4 + 4).
    assert_eq!(g.header.info.get("resolution").map(String::as_str), Some("16"));
    assert_eq!(g.header.info.get("samples_per_ray").map(String::as_str), Some("8"));
    assert!(gdrf_core::eval::provenance::trained_against_projected(&g.header));
    let g = load_generator(&dir.path("c").join("generator.safetensors"), Device::Cpu, Kind::Float).unwrap();
    assert!(gdrf_core::eval::provenance::trained_against_projected(&g.header));
}

#[test]
fn the_lazy_coverage_term_runs_every_kth_step_at_k_times_the_weight() {
    let dir = TempDir::new("train-lazy-coverage").unwrap();
    let mut every = tiny_config(&dir.0, "");
    every.loss.coverage_weight = 0.5;
    every.loss.coverage_candidates = 3;
    every.loss.coverage_resolution = 4;
    let lazy_cfg = TrainConfig { loss: LossConfig { coverage_interval: 2, ..every.loss.clone() }, ..every.clone() };
    let mut a = Trainer::new(every, &dir.path("every")).unwrap();
    a.prepare_data(&|_| {}).unwrap();
    let first = run_steps(&mut a, 1).remove(0);
    let mut lazy = Trainer::new(lazy_cfg, &dir.path("lazy")).unwrap();
    let runs = run_steps(&mut lazy, 3);
    let coverage = |r: &StepReport| r.g_terms.iter().find(|(k, _)| *k == "g_coverage").map(|t| t.1);
    // Step 0 is due: the same draws give the same MSE, weighed twice (0.5 · 2 instead of 0.5).
    let (c, c_lazy) = (coverage(&first).expect("a coverage term"), coverage(&runs[0]).expect("a coverage term"));
    assert_eq!(c.to_bits(), c_lazy.to_bits());
    let extra = runs[0].g_total - first.g_total;
    assert!((extra - 0.5 * c).abs() <= 1e-6 + 1e-5 * (0.5 * c).abs(), "G total grew by {extra}, expected {}", 0.5 * c);
    // … and the doubled weight reaches the gradient, not only the reported total.
    assert_ne!(first.grad_norm_g, runs[0].grad_norm_g);
    // Step 1 renders no coverage term; step 2 does again.
    assert_eq!(coverage(&runs[1]), None);
    assert!(coverage(&runs[2]).is_some_and(|c| c.is_finite() && c > 0.0));
}

#[test]
fn a_nan_step_is_skipped_and_repeated_ones_roll_back_with_halved_rates() {
    let dir = TempDir::new("train-guard").unwrap();
    let cfg = tiny_config(&dir.0, "[debug]\ninject_nonfinite_steps = [1, 6, 7, 8]\n\n[guard]\nrollback_after = 3");
    let mut t = Trainer::new(cfg, &dir.path("run")).unwrap();
    t.prepare_data(&|_| {}).unwrap();
    run_steps(&mut t, 1);
    let (g_before, d_before) = (params(t.generator_vars()), params(t.disc_vars()));
    let r = run_steps(&mut t, 1).remove(0);
    assert!(r.g_skipped && !r.d_skipped && r.g_total.is_nan());
    assert!(same_params(&g_before, &params(t.generator_vars())), "a skipped step leaves G untouched");
    assert!(!same_params(&d_before, &params(t.disc_vars())), "D still takes its finite step");
    assert_eq!((t.progress().skipped_steps, t.progress().consecutive_bad), (1, 1));
    // Steps 2–5 are clean (checkpoints after 2, 4 and 6 steps), then 6, 7, 8 fail.
    let reports = run_steps(&mut t, 7);
    let rolled: Vec<_> = reports.iter().filter_map(|r| r.rolled_back_to.map(|to| (r.step, to))).collect();
    assert_eq!(rolled, [(8, 8)], "the third bad step in a row (8) goes back to the newest checkpoint (after 8 steps)");
    assert_eq!(t.progress().rollbacks, 1);
    assert_eq!(t.progress().lr_scale, 0.5);
    assert_eq!(t.progress().skipped_steps, 4);
    let after = reports.last().unwrap();
    assert!(!after.g_skipped, "the replay runs clean");
    assert_eq!(after.lr_g, 0.5 * 3e-4);
    let events: Vec<_> =
        run::read_metrics(&dir.path("run")).unwrap().into_iter().filter(|m| m["event"] == "rollback").collect();
    assert_eq!(events.len(), 1);
    assert_eq!(events[0]["lr_scale"].as_f64(), Some(0.5));
}

#[test]
fn stage_switch_fade_in_and_ema_happen_at_the_configured_steps() {
    let dir = TempDir::new("train-stages").unwrap();
    let cfg = tiny_config(&dir.0, "");
    let mut t = Trainer::new(cfg, &dir.path("run")).unwrap();
    t.prepare_data(&|_| {}).unwrap();
    let mut seen = Vec::new();
    for _ in 0..6 {
        let decay = t.ema().next_decay();
        let shadow = params(t.ema_vars());
        let r = t.step().unwrap();
        // shadow ← shadow − (1 − d)(shadow − param), with the warm-up decay (1 + n)/(10 + n).
        let live = params(t.generator_vars());
        for ((name, s0), ((_, s1), (_, p))) in shadow.iter().zip(params(t.ema_vars()).iter().zip(&live)) {
            let want = s0 - (s0 - p) * (1.0 - decay);
            assert!(s1.allclose(&want, 1e-5, 1e-7, false), "EMA of {name} at step {}", r.step);
        }
        assert_eq!(decay, (2.0 + r.step as f64) / (11.0 + r.step as f64));
        seen.push((r.step, r.stage, r.resolution, r.alpha, r.lr_g));
    }
    assert_eq!(t.ema().updates, 6);
    assert_eq!(
        seen,
        [
            (0, 0, 8, 1.0, 2e-5),
            (1, 0, 8, 1.0, 2e-5),
            (2, 0, 8, 1.0, 2e-5),
            (3, 1, 16, 0.0, 3e-4),
            (4, 1, 16, 0.5, 3e-4),
            (5, 1, 16, 1.0, 3e-4),
        ]
    );
}

#[test]
fn a_stage_with_g_lr_zero_trains_the_discriminator_alone() {
    let dir = TempDir::new("train-d-only").unwrap();
    let mut cfg = tiny_config(&dir.0, "");
    cfg.stages[0].g_lr = Some(0.0);
    let mut t = Trainer::new(cfg, &dir.path("run")).unwrap();
    t.prepare_data(&|_| {}).unwrap();
    let (g0, e0, d0) = (params(t.generator_vars()), params(t.ema_vars()), params(t.disc_vars()));
    let reports = run_steps(&mut t, 3);
    assert!(same_params(&params(t.generator_vars()), &g0), "the generator moved in a discriminator-only stage");
    assert!(same_params(&params(t.ema_vars()), &e0), "the EMA moved in a discriminator-only stage");
    assert!(!same_params(&params(t.disc_vars()), &d0), "the discriminator did not train");
    assert_eq!(t.ema().updates, 0);
    for r in &reports {
        assert_eq!(r.lr_g, 0.0);
        assert!(r.g_total.is_nan() && r.g_terms.is_empty() && !r.g_skipped, "step {}", r.step);
        assert!(r.d_total.is_finite() && !r.d_skipped, "step {}", r.step);
    }
    assert_eq!(t.progress().skipped_steps, 0);
    // The metrics carry no generator figures for those steps.
    let metrics = std::fs::read_to_string(dir.path("run").join(run::METRICS)).unwrap();
    let first: serde_json::Value = serde_json::from_str(metrics.lines().next().unwrap()).unwrap();
    assert_eq!(first["g_total"], serde_json::Value::Null, "{first}");
    // The next stage (g_lr 3e-4) trains both.
    let r = run_steps(&mut t, 1);
    assert_eq!(r[0].lr_g, 3e-4);
    assert!(r[0].g_total.is_finite());
    assert!(!same_params(&params(t.generator_vars()), &g0));
    assert_eq!(t.ema().updates, 1);
}

#[test]
fn a_non_finite_state_is_never_checkpointed() {
    let dir = TempDir::new("train-nan-ckpt").unwrap();
    let mut t = Trainer::new(tiny_config(&dir.0, ""), &dir.path("run")).unwrap();
    t.prepare_data(&|_| {}).unwrap();
    run_steps(&mut t, 2);
    // Every checkpoint file with its bytes: a save that wrote a new file or overwrote the
    // step's own checkpoint changes this.
    let files = || -> Vec<(std::path::PathBuf, Vec<u8>)> {
        let list = run::list_checkpoints(&dir.path("run")).unwrap();
        list.into_iter().map(|(_, p)| (p.clone(), std::fs::read(&p).unwrap())).collect()
    };
    let before = files();
    let _ = tch::no_grad(|| t.generator_vars().variables()["template.sigma_head.bias"].shallow_clone().fill_(f64::NAN));
    let e = t.save_checkpoint().unwrap_err().to_string();
    assert!(e.contains("generator.template.sigma_head.bias") && e.contains("NaN"), "{e}");
    assert!(files() == before, "nothing was written");
}

/// The one-render step equals the release's two renders of the same images: its
/// discriminator update is the release's D step on the generator's draws (which renders
/// them again without gradients), and its generator gradient, taken on the kept graph
/// through the updated discriminator, is the release's generator pass (which renders them
/// again with gradients) through that discriminator. Both with the mode-seeking pairs, in
/// two chunks, with R1 due and DiffAugment's draws on.
#[test]
fn the_one_render_step_equals_two_renders_of_the_same_images() {
    one_render_equals_two_renders("train-one-render", Background::Learned);
}

/// On random backgrounds the fakes of both steps are composited on the same colours (pairs
/// of the mode-seeking term sharing one).
#[test]
fn the_one_render_step_equals_two_renders_on_random_backgrounds() {
    one_render_equals_two_renders("train-one-render-random", Background::Random);
}

fn one_render_equals_two_renders(name: &str, background: Background) {
    let dir = TempDir::new(name).unwrap();
    let mut cfg = tiny_config(&dir.0, "");
    cfg.generator.background = background;
    cfg.stages.truncate(1);
    cfg.stages[0].batch_size = 4;
    cfg.stages[0].batch_split = 2;
    cfg.loss.diversity_weight = 5.0;
    cfg.discriminator.augment = vec![Augmentation::Translation, Augmentation::Cutout];
    assert!(cfg.loss.r1_due(0));
    let mut two = Trainer::new(cfg.clone(), &dir.path("two")).unwrap();
    two.prepare_data(&|_| {}).unwrap();
    cfg.step = gdrf_core::train::StepKind::OneRender;
    let mut one = Trainer::new(cfg, &dir.path("one")).unwrap();
    let d0 = params(one.disc_vars());
    assert!(
        same_params(&d0, &params(two.disc_vars()))
            && same_params(&params(one.generator_vars()), &params(two.generator_vars()))
    );

    let terms_one = one.one_render_gradients_now().unwrap();
    two.discriminator_step_on_generator_draws_now().unwrap();
    let terms_two = two.generator_gradients_now().unwrap();

    // The same discriminator update, and it did move.
    let (d_one, d_two) = (params(one.disc_vars()), params(two.disc_vars()));
    assert!(!same_params(&d_one, &d0));
    let mut moved = 0;
    for (((name, a), (_, b)), (_, before)) in d_one.iter().zip(&d_two).zip(&d0) {
        assert!(a.allclose(b, 1e-5, 1e-7, false), "D {name}: max |Δ| {}", max_abs(&(a - b)));
        moved += (!a.equal(before)) as usize;
    }
    assert!(moved > 5, "{moved} D tensors moved");
    // The same generator loss and gradient through the updated discriminator.
    let names: Vec<_> = terms_one.iter().map(|t| t.0).collect();
    assert!(names.contains(&"g_diversity") && names.contains(&"reg_smoothness"), "{names:?}");
    for ((na, va), (nb, vb)) in terms_one.iter().zip(&terms_two) {
        assert_eq!(na, nb);
        assert!((va - vb).abs() <= 1e-5 * (1.0 + vb.abs()), "{na}: {va} against {vb}");
    }
    let (ga, gb) = (one.generator_vars().variables(), two.generator_vars().variables());
    let mut checked = 0;
    for (name, a) in &ga {
        let (a, b) = (a.grad(), gb[name].grad());
        assert!(a.defined() && b.defined(), "{name} has a gradient in both");
        let scale = max_abs(&b);
        assert!(a.allclose(&b, 1e-4, 1e-6 * scale.max(1e-12), false), "G {name}: max |Δ| {}", max_abs(&(&a - &b)));
        checked += (scale > 0.0) as usize;
    }
    assert!(checked > 20, "{checked} non-zero G gradients");
    // And it is a step of its own in the loop: a patch stage is refused by name.
    let mut bad = tiny_config(&dir.0, "step = \"one-render\"");
    bad.stages[0].regions = 4;
    let e = bad.validate().unwrap_err().to_string();
    assert!(e.contains("one-render") && e.contains("stages[0].regions"), "{e}");
}

fn max_abs(t: &Tensor) -> f64 {
    f64::try_from(t.abs().max()).unwrap()
}

/// The two-pass patch step (no-grad render, D's gradient w.r.t. the image, each band
/// re-rendered with gradients at the same depths) gives the single-pass gradient.
#[test]
fn the_two_pass_patch_step_gives_the_single_pass_gradient() {
    let dir = TempDir::new("train-patches").unwrap();
    let mut cfg = tiny_config(&dir.0, "");
    cfg.stages.truncate(1);
    cfg.stages[0].resolution = 16;
    cfg.stages[0].batch_size = 4;
    cfg.stages[0].batch_split = 2;
    let mut single = Trainer::new(cfg.clone(), &dir.path("a")).unwrap();
    single.prepare_data(&|_| {}).unwrap();
    cfg.stages[0].regions = 4;
    let mut patched = Trainer::new(cfg, &dir.path("b")).unwrap();
    let la = single.generator_gradients_now().unwrap();
    let lb = patched.generator_gradients_now().unwrap();
    for ((na, va), (nb, vb)) in la.iter().zip(&lb) {
        assert_eq!(na, nb);
        assert!((va - vb).abs() <= 1e-5 * (1.0 + va.abs()), "{na}: {va} vs {vb}");
    }
    let (ga, gb) = (single.generator_vars().variables(), patched.generator_vars().variables());
    let mut checked = 0;
    for (name, a) in &ga {
        let (a, b) = (a.grad(), gb[name].grad());
        assert!(a.defined() && b.defined(), "{name} has a gradient in both");
        // Element-wise: |a − b| ≤ atol + rtol·|b|.
        let scale = f64::try_from(a.abs().max()).unwrap();
        let ok = a.allclose(&b, 1e-3, 1e-6 * scale.max(1e-12), false);
        assert!(ok, "{name}: max |Δ| {}", f64::try_from((&a - &b).abs().max()).unwrap());
        checked += 1;
    }
    assert!(checked > 20);
    assert!(
        patched.disc_vars().trainable_variables().iter().all(|p| !p.grad().defined()),
        "D gets no gradient from the G step"
    );
}

#[test]
fn every_shipped_config_loads_and_validates() {
    let dir = common::repo_root().join("configs");
    let mut names = Vec::new();
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            let cfg = TrainConfig::load(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            assert!(cfg.schedule.total_steps > cfg.stages.last().unwrap().from_step, "{}", path.display());
            names.push(path.file_stem().unwrap().to_string_lossy().into_owned());
        }
    }
    names.sort();
    assert_eq!(
        names,
        ["carla", "cars", "chairs", "chairs-campaign", "chairs-campaign-cpu", "chairs-campaign-gpu", "chairs-tiny"]
    );
}

/// The campaign's two continuation configs hold the same keys but for the GPU's float32
/// (the CPU's "auto": bfloat16 where the CPU has bfloat16 instructions), the CPU's one
/// thread, and batch 32, in
/// all five stages: step 0's, from step 140 231 the same at a quarter of the learning
/// rates, from step 205 046 the same at 64² on the scaled-patch step (32² patches, whose
/// discriminator input, what the 32² stages trained, fades nothing in), with the curve
/// evaluated at 64², and from step 227 393 the same with larger patches, a quarter of them
/// at native resolution (half from step 227 651); the pose terms on whole-chair patches at the weight that makes up
/// for their count; from step 229 350 the opacity term.
#[test]
fn the_campaign_gpu_config_differs_from_the_cpu_one_in_precision_threads_and_batch_only() {
    use gdrf_core::train::config::Precision;
    let dir = common::repo_root().join("configs");
    let cpu = TrainConfig::load(&dir.join("chairs-campaign-cpu.toml")).unwrap();
    let mut gpu = TrainConfig::load(&dir.join("chairs-campaign-gpu.toml")).unwrap();
    assert_eq!((cpu.precision, gpu.precision), (Precision::Auto, Precision::Float32));
    let batches = |c: &TrainConfig| c.stages.iter().map(|s| s.batch_size).collect::<Vec<_>>();
    assert_eq!((batches(&cpu), batches(&gpu)), (vec![8; 6], vec![32; 6]));
    assert_eq!((cpu.optim.g_lr, cpu.optim.d_lr), (1e-4, 2e-4));
    assert_eq!(cpu.stages[1].from_step, 140_231);
    assert_eq!((cpu.learning_rates(140_230), cpu.learning_rates(140_231)), ((1e-4, 2e-4), (2.5e-5, 5e-5)));
    // Only the learning rates change at step 140 231: no new resolution, so no fade-in.
    let mut quarter = cpu.stages[1].clone();
    (quarter.from_step, quarter.g_lr, quarter.d_lr) = (0, None, None);
    assert_eq!(quarter, cpu.stages[0]);
    assert_eq!(cpu.alpha(140_231), 1.0);
    // From step 205 046 only the resolution and the patches change; the discriminator still
    // judges 32² inputs, so nothing fades in.
    let mut at64 = cpu.stages[2].clone();
    assert_eq!((at64.from_step, at64.resolution), (205_046, 64));
    let p = at64.patch.take().expect("the 64² stage's patches");
    assert_eq!((p.size, p.beta_start, p.beta_end, p.anneal_images), (32, 0.001, 0.8, 80_000));
    (at64.from_step, at64.resolution) = (cpu.stages[1].from_step, 32);
    assert_eq!(at64, cpu.stages[1]);
    assert_eq!(cpu.switch_step(205_046), None);
    assert_eq!([cpu.alpha(205_045), cpu.alpha(205_046), cpu.alpha(215_046)], [1.0, 1.0, 1.0]);
    assert_eq!((cpu.eval.resolution, cpu.eval.swap), (64, 16));
    // From step 227 393 only the patches change (final β 0.8 to 0.4, a quarter of them at
    // native resolution) and the pose weight: nothing fades in.
    let mut native = cpu.stages[3].clone();
    assert_eq!((native.from_step, native.pose_weight), (227_393, Some(38.1)));
    let n = native.patch.as_mut().expect("the larger patches with a native share");
    assert_eq!((n.beta_end, n.native_share), (0.4, 0.25));
    (n.beta_end, n.native_share) = (p.beta_end, 0.0);
    (native.from_step, native.pose_weight) = (cpu.stages[2].from_step, None);
    assert_eq!(native, cpu.stages[2]);
    assert_eq!((cpu.switch_step(227_393), cpu.alpha(227_393)), (None, 1.0));
    // From step 215 145 the pose terms count only patches of at least 0.9 of the side; their
    // weight is 15 over the share of patches counted at the final β (scale
    // P/R + (1 − P/R)·x, x ~ Beta(1, β); native patches never count), so a counted patch
    // weighs what a 32² image did: 54 at β 0.8 (from step 226 201), 38.1 at β 0.4 with a
    // quarter native (from step 227 393).
    assert_eq!(cpu.loss.pose_min_scale, 0.9);
    assert_eq!([226_201, 227_392, 227_393].map(|s| cpu.loss_at(s).pose_weight), [54.0, 54.0, 38.1]);
    let min_scale = p.size as f64 / 64.0;
    let x = (cpu.loss.pose_min_scale - min_scale) / (1.0 - min_scale);
    let counted = |beta: f64| (1.0 - x).powf(beta);
    assert!((counted(0.8) - 0.276).abs() < 5e-4, "{}", counted(0.8));
    assert!((counted(0.4) - 0.525).abs() < 5e-4, "{}", counted(0.4));
    // From step 227 651 half the patches are native: 57.1 = 15 / (0.5 · counted(0.4)).
    let mut half = cpu.stages[4].clone();
    assert_eq!((half.from_step, half.pose_weight), (227_651, Some(57.1)));
    let h = half.patch.as_mut().expect("the half-native patches");
    assert_eq!(h.native_share, 0.5);
    h.native_share = 0.25;
    (half.from_step, half.pose_weight) = (cpu.stages[3].from_step, cpu.stages[3].pose_weight);
    assert_eq!(half, cpu.stages[3]);
    assert_eq!([227_650, 227_651].map(|s| cpu.loss_at(s).pose_weight), [38.1, 57.1]);
    assert_eq!((cpu.switch_step(227_651), cpu.alpha(227_651)), (None, 1.0));
    for (step, share, tolerance) in
        [(227_392, counted(0.8), 0.5), (227_393, 0.75 * counted(0.4), 0.05), (227_651, 0.5 * counted(0.4), 0.05)]
    {
        let w = cpu.loss_at(step).pose_weight;
        assert!((15.0 / share - w).abs() < tolerance, "step {step}: {w}");
    }
    // From step 229 350 only the opacity term comes on (weight 1); nothing fades in, and the
    // loss before that step has no opacity term.
    let mut opaque = cpu.stages[5].clone();
    assert_eq!((opaque.from_step, opaque.opacity_weight), (229_350, Some(1.0)));
    (opaque.from_step, opaque.opacity_weight) = (cpu.stages[4].from_step, None);
    assert_eq!(opaque, cpu.stages[4]);
    assert_eq!([229_349, 229_350].map(|s| cpu.loss_at(s).opacity_weight), [0.0, 1.0]);
    assert_eq!(cpu.loss_at(229_350).pose_weight, 57.1);
    assert_eq!((cpu.switch_step(229_350), cpu.alpha(229_350)), (None, 1.0));
    // The CPU's run keeps to one thread (the other core's jobs would starve a second one).
    assert_eq!((cpu.threads, gpu.threads), (1, 0));
    (gpu.precision, gpu.threads) = (cpu.precision, cpu.threads);
    for (g, c) in gpu.stages.iter_mut().zip(&cpu.stages) {
        g.batch_size = c.batch_size;
    }
    assert_eq!(gpu, cpu);
}

#[test]
fn bfloat16_training_steps_stay_finite() {
    let dir = TempDir::new("train-bf16").unwrap();
    let mut t = Trainer::new(tiny_config(&dir.0, "precision = \"bfloat16\""), &dir.path("run")).unwrap();
    t.prepare_data(&|_| {}).unwrap();
    for _ in 0..2 {
        let r = t.step().unwrap();
        assert!(!r.g_skipped && !r.d_skipped && r.g_total.is_finite() && r.d_total.is_finite(), "{r:?}");
    }
    assert!(t.generator_vars().variables().values().all(|v| v.kind() == Kind::Float), "master weights stay float32");
}

#[test]
fn a_run_continues_under_a_longer_schedule_but_not_with_other_networks() {
    let dir = TempDir::new("train-extend").unwrap();
    let mut cfg = tiny_config(&dir.0, "");
    cfg.schedule.total_steps = 3;
    let mut t = Trainer::new(cfg.clone(), &dir.path("run")).unwrap();
    t.prepare_data(&|_| {}).unwrap();
    assert_eq!(t.run(RunLimits::default(), &never(), |_, _| {}).unwrap(), Stopped::Finished);
    let mut longer = cfg.clone();
    longer.schedule.total_steps = 5;
    let mut t = Trainer::resume_with(&dir.path("run"), longer).unwrap();
    assert_eq!(t.progress().step, 3);
    assert_eq!(t.run(RunLimits::default(), &never(), |_, _| {}).unwrap(), Stopped::Finished);
    assert_eq!(t.progress().step, 5);
    assert_eq!(TrainConfig::load(&dir.path("run").join(run::CONFIG)).unwrap().schedule.total_steps, 5);
    let mut wider = cfg;
    wider.generator.hidden_dim = 16;
    let e = Trainer::resume_with(&dir.path("run"), wider).err().unwrap().to_string();
    assert!(e.contains("[generator]"), "{e}");
}

#[test]
fn a_run_can_start_from_an_exported_generator() {
    let dir = TempDir::new("train-init").unwrap();
    let cfg = tiny_config(&dir.0, "");
    let mut a = Trainer::new(cfg.clone(), &dir.path("a")).unwrap();
    a.prepare_data(&|_| {}).unwrap();
    run_steps(&mut a, 3);
    let export = dir.path("a").join(run::GENERATOR);
    let exported = load_generator(&export, Device::Cpu, Kind::Float).unwrap();

    // Another seed: without the file the weights would differ.
    let mut warm = tiny_config(&dir.0, "");
    warm.seed = 6;
    warm.init_generator = Some(export.clone());
    let b = Trainer::new(warm.clone(), &dir.path("b")).unwrap();
    assert!(same_params(&params(b.generator_vars()), &params(&exported.vs)));
    assert!(same_params(&params(b.ema_vars()), &params(&exported.vs)));
    warm.init_generator = None;
    let cold = Trainer::new(warm.clone(), &dir.path("c")).unwrap();
    assert!(!same_params(&params(cold.generator_vars()), &params(&exported.vs)));
    assert!(same_params(&params(b.disc_vars()), &params(cold.disc_vars())), "the discriminator starts from the seed");

    // Another architecture, or no such file: an error naming the key.
    let mut wide = warm.clone();
    wide.generator.hidden_dim = 16;
    wide.init_generator = Some(export);
    let e = Trainer::new(wide, &dir.path("d")).err().expect("a wider generator is refused").to_string();
    assert!(e.contains("init_generator") && e.contains("[generator]"), "{e}");
    warm.init_generator = Some(dir.path("missing.safetensors"));
    let e = Trainer::new(warm, &dir.path("e")).err().expect("a missing file is refused").to_string();
    assert!(e.contains("init_generator") && e.contains("missing.safetensors"), "{e}");
}

#[test]
fn previews_neither_draw_from_nor_depend_on_the_global_generator() {
    let dir = TempDir::new("train-previews").unwrap();
    let t = Trainer::new(tiny_config(&dir.0, ""), &dir.path("run")).unwrap();
    let randn = || Tensor::randn([16], (Kind::Float, Device::Cpu));
    let (first, after) =
        gdrf_core::rng::with_global_seed(1, || (gdrf_core::train::samples::render_previews(&t).unwrap(), randn()));
    assert!(after.equal(&gdrf_core::rng::with_global_seed(1, randn)), "the previews drew from libtorch's generator");
    let second = gdrf_core::rng::with_global_seed(2, || gdrf_core::train::samples::render_previews(&t).unwrap());
    assert!(
        first.samples.equal(&second.samples)
            && first.swap.equal(&second.swap)
            && first.template.equal(&second.template)
    );
}

/// The newest checkpoint truncated, with a flipped bit, or with a NaN written over a value:
/// resume names it, resumes from the one before and says why; with every checkpoint
/// damaged it is an error listing each one tried.
#[test]
fn a_damaged_newest_checkpoint_is_passed_over() {
    let dir = TempDir::new("train-damaged").unwrap();
    let run_dir = dir.path("run");
    let mut t = Trainer::new(tiny_config(&dir.0, ""), &run_dir).unwrap();
    t.prepare_data(&|_| {}).unwrap();
    run_steps(&mut t, 4);
    drop(t);
    let list = run::list_checkpoints(&run_dir).unwrap();
    let [(older_step, older), (4, newest)] = &list[..] else { panic!("checkpoints {list:?}") };
    let good = std::fs::read(newest).unwrap();
    let nan = |b: &mut Vec<u8>| {
        let n = b.len();
        b[n - 4..].copy_from_slice(&f32::NAN.to_le_bytes());
    };
    // A header (outside the checksum) whose generator is a million times wider than the
    // tensors stored: refused before the networks are built, which would allocate ~1 PB.
    let wide = |b: &mut Vec<u8>| {
        let n = u64::from_le_bytes(b[..8].try_into().unwrap()) as usize;
        let json = std::str::from_utf8(&b[8..8 + n]).unwrap();
        let key = "\\\"hidden_dim\\\":";
        assert!(json.contains(key), "{json}");
        let json = json.replace(key, &format!("{key}1600000"));
        let mut out = (json.len() as u64).to_le_bytes().to_vec();
        out.extend_from_slice(json.as_bytes());
        out.extend_from_slice(&b[8 + n..]);
        *b = out;
    };
    // A discriminator 2.5 billion times wider than stored (~1 TB), the same way.
    let wide_d = |b: &mut Vec<u8>| {
        let n = u64::from_le_bytes(b[..8].try_into().unwrap()) as usize;
        let json = std::str::from_utf8(&b[8..8 + n]).unwrap();
        let key = "\\\"channels\\\":[";
        assert!(json.contains(key), "{json}");
        let json = json.replace(key, &format!("{key}1000000000"));
        let mut out = (json.len() as u64).to_le_bytes().to_vec();
        out.extend_from_slice(json.as_bytes());
        out.extend_from_slice(&b[8 + n..]);
        *b = out;
    };
    // (what the error names, how the file is damaged); some damages change its length.
    type Damage<'a> = (&'a str, &'a dyn Fn(&mut Vec<u8>));
    let damages: [Damage; 5] = [
        ("truncated", &|b| b.truncate(b.len() / 2)),
        ("checksum", &|b| *b.last_mut().unwrap() ^= 1),
        ("NaN", &nan),
        ("far more than", &wide),
        ("more than any tensor it stores holds", &wide_d),
    ];
    for (why, damage) in damages {
        let mut bytes = good.clone();
        damage(&mut bytes);
        std::fs::write(newest, &bytes).unwrap();
        let t = Trainer::resume(&run_dir, None).unwrap();
        assert_eq!(t.progress().step, *older_step, "{why}");
        let skipped = t.skipped_checkpoints();
        assert_eq!(skipped.len(), 1, "{why}: {skipped:?}");
        assert_eq!(&skipped[0].0, newest);
        assert!(skipped[0].1.contains(why) && skipped[0].1.contains("step-00000004"), "{}", skipped[0].1);
    }
    std::fs::write(newest, &good).unwrap();
    assert!(Trainer::resume(&run_dir, None).unwrap().skipped_checkpoints().is_empty());
    // Nothing loads: the error lists both files, newest first.
    std::fs::write(newest, &good[..good.len() / 2]).unwrap();
    std::fs::write(older, b"").unwrap();
    let e = Trainer::resume(&run_dir, None).err().expect("no checkpoint loads").to_string();
    let (at_newest, at_older) = (e.find("step-00000004"), e.find(older.file_name().unwrap().to_str().unwrap()));
    assert!(e.contains("no checkpoint loads") && at_newest.is_some() && at_newest < at_older, "{e}");
}

/// A run directory missing its config, its metrics or its samples folder still resumes
/// from its checkpoints (they hold the config), and carries on writing.
#[test]
fn a_run_directory_missing_its_config_metrics_or_samples_resumes() {
    let dir = TempDir::new("train-partial").unwrap();
    let run_dir = dir.path("run");
    let mut t = Trainer::new(tiny_config(&dir.0, ""), &run_dir).unwrap();
    t.prepare_data(&|_| {}).unwrap();
    run_steps(&mut t, 4);
    drop(t);
    std::fs::remove_file(run_dir.join(run::CONFIG)).unwrap();
    std::fs::remove_file(run_dir.join(run::METRICS)).unwrap();
    std::fs::remove_dir_all(run_dir.join(run::SAMPLES)).unwrap();
    let mut t = Trainer::resume(&run_dir, None).unwrap();
    assert_eq!(t.progress().step, 4);
    t.prepare_data(&|_| {}).unwrap();
    run_steps(&mut t, 2);
    let steps: Vec<i64> = run::read_metrics(&run_dir).unwrap().iter().filter_map(|l| l["step"].as_i64()).collect();
    assert_eq!(steps, [4, 5]);
    assert_eq!(run::latest_checkpoint(&run_dir).unwrap().0, 6);
}

/// With `generator.background = "random"` the discriminator sees each real image on a colour
/// of its own where the alpha is 0, and unchanged where it is 1; a dataset without
/// transparency is refused, naming it.
#[test]
fn random_backgrounds_composite_the_real_images_through_their_alpha() {
    let colours = composites_real_images_through_their_alpha("train-random-background", Background::Random);
    assert_ne!(colours[0], colours[1], "a colour per image");
}

/// With `generator.background = "corners"` the same, on corners of the RGB cube: the
/// uniform colours of `random` rounded to the nearest corner (in the images' [-1, 1]: each
/// channel's sign).
#[test]
fn corner_backgrounds_composite_the_real_images_through_their_alpha() {
    let uniform = composites_real_images_through_their_alpha("train-uniform-background", Background::Random);
    let corners = composites_real_images_through_their_alpha("train-corner-background", Background::Corners);
    let rounded: Vec<Vec<f64>> =
        uniform.iter().map(|c| c.iter().map(|&v| if v >= 0.0 { 1.0 } else { -1.0 }).collect()).collect();
    assert_eq!(corners, rounded);
}

/// The colour `(B, 3)` in [-1, 1] each judged real image shows where its alpha is 0.
fn composites_real_images_through_their_alpha(name: &str, background: Background) -> Vec<Vec<f64>> {
    let dir = TempDir::new(name).unwrap();
    // Left half opaque (a colour per image), right half transparent.
    let halves = dir.path("halves");
    std::fs::create_dir_all(&halves).unwrap();
    for i in 0..4u8 {
        let img = image::ImageBuffer::from_fn(8, 8, |x, _| {
            if x < 4 {
                image::Rgba([40 * i, 200, 90, 255])
            } else {
                image::Rgba([0, 0, 0, 0])
            }
        });
        img.save(halves.join(format!("{i}.png"))).unwrap();
    }
    let mut cfg = tiny_config(&dir.0, "");
    cfg.stages.truncate(1);
    cfg.data.path = halves;
    cfg.data.synth = None;
    cfg.data.require_poses = false;
    let white = Trainer::new(cfg.clone(), &dir.path("white")).unwrap().judged_real_now().unwrap();
    cfg.generator.background = background;
    let real = Trainer::new(cfg.clone(), &dir.path("random")).unwrap().judged_real_now().unwrap();
    assert_eq!(real.size(), [2, 3, 8, 8]);
    let (left, right) = (|t: &Tensor| t.narrow(3, 0, 4), |t: &Tensor| t.narrow(3, 4, 4));
    assert!(left(&real).equal(&left(&white)), "opaque pixels unchanged");
    assert_eq!(f64::try_from(right(&white).min()).unwrap(), 1.0, "transparent pixels are white on white");
    let mut colours = Vec::new();
    for b in 0..2 {
        let c: Vec<f64> = (0..3)
            .map(|k| {
                let v = right(&real).get(b).get(k);
                let (lo, hi) = (f64::try_from(v.min()).unwrap(), f64::try_from(v.max()).unwrap());
                assert_eq!(lo, hi, "image {b}: one colour where the alpha is 0");
                assert!((-1.0..=1.0).contains(&lo), "{lo}");
                lo
            })
            .collect();
        colours.push(c);
    }

    let opaque = dir.path("opaque");
    std::fs::create_dir_all(&opaque).unwrap();
    for i in 0..4u8 {
        image::ImageBuffer::from_pixel(8, 8, image::Rgb([i * 50, 9, 9])).save(opaque.join(format!("{i}.png"))).unwrap();
    }
    cfg.data.path = opaque.clone();
    let e = Trainer::new(cfg, &dir.path("bad")).unwrap().step().expect_err("no alpha").to_string();
    assert!(e.contains(&opaque.display().to_string()) && e.contains("transparent pixel"), "{e}");
    assert!(e.contains(&format!("\"{}\"", background.name())), "{e}");
    colours
}

/// Runs `cfg` to its end in DIR/a, then copies that run folder to each of `copies`.
fn finished_run_copied(dir: &TempDir, cfg: &TrainConfig, copies: &[&str]) {
    let mut t = Trainer::new(cfg.clone(), &dir.path("a")).unwrap();
    t.prepare_data(&|_| {}).unwrap();
    assert_eq!(t.run(RunLimits::default(), &never(), |_, _| {}).unwrap(), Stopped::Finished);
    drop(t);
    for c in copies {
        copy_dir(&dir.path("a"), &dir.path(c));
    }
}

/// A run switches to random backgrounds by `--resume --config` (the one [generator] key that
/// may change), continues exactly after a resume, and exports a generator that says so.
#[test]
fn a_run_switches_to_random_backgrounds_and_resumes_exactly() {
    let dir = TempDir::new("train-switch-background").unwrap();
    let mut cfg = tiny_config(&dir.0, "");
    cfg.schedule.total_steps = 2;
    cfg.schedule.checkpoint_interval = 100;
    finished_run_copied(&dir, &cfg, &["b"]);
    let mut random = cfg.clone();
    random.schedule.total_steps = 10;
    random.generator.background = Background::Random;
    let mut other = random.clone();
    other.generator.hidden_dim = 16;
    let e = Trainer::resume_with(&dir.path("a"), other).err().unwrap().to_string();
    assert!(e.contains("[generator]"), "{e}");

    let mut a = Trainer::resume_with(&dir.path("a"), random.clone()).unwrap();
    let full = run_steps(&mut a, 4);
    let mut b = Trainer::resume_with(&dir.path("b"), random).unwrap();
    run_steps(&mut b, 2);
    drop(b);
    let mut b = Trainer::resume(&dir.path("b"), None).unwrap();
    assert_eq!(b.progress().step, 4);
    let rest = run_steps(&mut b, 2);
    for (x, y) in full[2..].iter().zip(&rest) {
        assert_eq!(
            (x.d_total.to_bits(), x.g_total.to_bits()),
            (y.d_total.to_bits(), y.g_total.to_bits()),
            "step {}",
            x.step
        );
    }
    assert!(same_params(&params(a.generator_vars()), &params(b.generator_vars())));
    let exported = load_generator(&dir.path("b").join(run::GENERATOR), Device::Cpu, Kind::Float).unwrap();
    assert_eq!(exported.generator.cfg.background, Background::Random);
    // The checkpoint written before the switch keeps the background it was trained with.
    let ckpts = run::list_checkpoints(&dir.path("a")).unwrap();
    assert_eq!(ckpts.iter().map(|c| c.0).collect::<Vec<_>>(), [2, 6]);
    let before = load_generator(&ckpts[0].1, Device::Cpu, Kind::Float).unwrap();
    assert_eq!(before.generator.cfg.background, Background::Learned);
}

/// The training-time occupancy grid (`[occupancy]`): a run switches it on by `--resume
/// --config`, and the next step builds it; the step's renders are clipped by it (the step
/// differs from the same step without it); its scores are saved with the state, and a run
/// resumed between two refreshes continues exactly, which it can only do from the saved
/// scores (after two refreshes they hold a decayed ½ that no single build gives).
#[test]
fn a_run_switches_the_training_grid_on_and_resumes_exactly() {
    use gdrf_core::train::config::OccupancyConfig;
    use gdrf_core::train::occupancy::SCORE_TENSOR;
    let dir = TempDir::new("train-occupancy").unwrap();
    let mut cfg = tiny_config(&dir.0, "");
    // The campaign's generator, whose chairs leave most of the cube empty (a fresh tiny
    // one's density is about the same everywhere, so a grid is all or nothing).
    let campaign = common::repo_root().join("models/chairs-campaign/generator.safetensors");
    let loaded = load_generator(&campaign, Device::Cpu, Kind::Float)
        .unwrap_or_else(|e| panic!("the committed campaign model is needed: {e}"));
    cfg.generator = loaded.generator.cfg.clone();
    cfg.init_generator = Some(campaign);
    cfg.schedule.total_steps = 2;
    cfg.schedule.checkpoint_interval = 100;
    finished_run_copied(&dir, &cfg, &["b", "plain"]);
    let mut plain_cfg = cfg.clone();
    plain_cfg.schedule.total_steps = 10;
    let mut gridded = plain_cfg.clone();
    gridded.occupancy = Some(OccupancyConfig { every: 3, codes: 2, resolution: 16, threshold: 0.5, decay: 0.5 });

    let without = run_steps(&mut Trainer::resume_with(&dir.path("plain"), plain_cfg).unwrap(), 1);
    let mut a = Trainer::resume_with(&dir.path("a"), gridded.clone()).unwrap();
    assert!(a.occupancy_grid().is_none(), "a run without a grid resumes without one");
    // Steps 2 to 5: the grid is built at 2, refreshed at 3 and used as it is at 4 and 5.
    let full = run_steps(&mut a, 4);
    let fractions: Vec<f64> = full.iter().map(|r| r.occupancy.unwrap()).collect();
    println!("occupied fractions {fractions:?}");
    assert!(fractions.iter().all(|&f| f > 0.0 && f < 1.0), "a grid that clips some rays and not all: {fractions:?}");
    assert_ne!(
        (without[0].d_total.to_bits(), without[0].g_total.to_bits()),
        (full[0].d_total.to_bits(), full[0].g_total.to_bits()),
        "the grid changes the step's renders"
    );
    let score = &a.occupancy_grid().unwrap().score;
    let between = i64::try_from(score.gt(0.0).logical_and(&score.lt(1.0)).sum(Kind::Int64)).unwrap();
    assert!(between > 0, "after two refreshes, cells seen only by the first score ½");

    let mut b = Trainer::resume_with(&dir.path("b"), gridded).unwrap();
    run_steps(&mut b, 2); // steps 2 and 3, then a checkpoint
    drop(b);
    let (_, newest) = run::latest_checkpoint(&dir.path("b")).unwrap();
    assert!(gdrf_core::checkpoint::load(&newest).unwrap().tensors.contains_key(SCORE_TENSOR));
    let mut b = Trainer::resume(&dir.path("b"), None).unwrap();
    assert_eq!(b.progress().step, 4);
    let rest = run_steps(&mut b, 2);
    for (x, y) in full[2..].iter().zip(&rest) {
        assert_eq!(
            (x.d_total.to_bits(), x.g_total.to_bits(), x.grad_norm_g.to_bits()),
            (y.d_total.to_bits(), y.g_total.to_bits(), y.grad_norm_g.to_bits()),
            "step {}",
            x.step
        );
        assert_eq!(x.occupancy, y.occupancy);
    }
    assert!(same_params(&params(a.generator_vars()), &params(b.generator_vars())));
    assert!(same_params(&params(a.disc_vars()), &params(b.disc_vars())));
    assert!(a.occupancy_grid().unwrap().score.equal(&b.occupancy_grid().unwrap().score));
}
