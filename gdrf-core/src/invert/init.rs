//! Stage 1 of the inversion (paper §5.2): a ResNet-34 F (tch's architecture, trained from
//! scratch) that predicts a photo's shape feature w_s and camera pose, trained on images the
//! generator renders from random codes and poses. Its w_s starts the optimisation, and its
//! pose stands in for a pose the user does not know.
//!
//! Loss per batch: `mean (F_w(I) − w_s)² + pose_weight · pose error + image_weight ·
//! MSE(I(F_w(I), γ_a, β_a, θ), I)`, the pose error being (pitch − pitch*)² + (cos yaw −
//! cos yaw*)² + (sin yaw − sin yaw*)² (the yaw is predicted as a unit vector, so ±π is no
//! edge). The last term is the paper's re-rendering loss without its LPIPS part; it renders
//! every training image again with gradients, so it is off by default on CPUs.
use crate::camera::Poses;
use crate::checkpoint::{load_tensors_with, tensors_to_bytes};
use crate::config::{CameraConfig, RenderConfig};
use crate::field::generator::Generator;
use crate::io::resize;
use crate::nn::film::Film;
use crate::paths::write_atomic;
use crate::render::{Noise, Renderer};
use crate::rng::{Purpose, RandomSource, StepRng};
use crate::train::optim::{zero_grads, Adam};
use crate::{Error, Latents, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;
use tch::nn::{self, ModuleT};
use tch::{Device, Kind, Tensor};

/// Metadata key of an initialiser file's JSON header.
pub const INIT_KEY: &str = "gdrf_initialiser";

/// Settings of the initialiser's training.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct InitConfig {
    /// Side of the generated training images (and of F's input).
    pub resolution: i64,
    /// Samples per ray of the training renders (coarse; as many importance samples);
    /// `num_steps` in files written before it was named so.
    #[serde(alias = "num_steps")]
    pub samples: usize,
    /// Generated (image, pose, w_s, γ_a, β_a) tuples; the last `held_out` are validation.
    pub count: i64,
    pub held_out: i64,
    pub batch_size: i64,
    pub steps: i64,
    pub lr: f64,
    pub pose_weight: f64,
    /// Weight of the re-rendering term (0 = off).
    pub image_weight: f64,
    /// Side of the re-rendering term's renders.
    pub image_resolution: i64,
    /// Validation every this many steps (and at the end).
    pub eval_interval: i64,
    pub seed: u64,
}

impl Default for InitConfig {
    fn default() -> Self {
        Self {
            resolution: 64,
            samples: 12,
            count: 4096,
            held_out: 256,
            batch_size: 32,
            steps: 2000,
            lr: 1e-3,
            pose_weight: 1.0,
            image_weight: 0.0,
            image_resolution: 32,
            eval_interval: 250,
            seed: 0,
        }
    }
}

impl InitConfig {
    pub fn validate(&self) -> Result<()> {
        let bad = |k: &str, v: String, want: &str| Err(Error::Config(format!("init.{k} is {v}, expected {want}")));
        if !(16..=512).contains(&self.resolution) {
            return bad("resolution", self.resolution.to_string(), "16 to 512");
        }
        if self.samples < 3 {
            return bad("samples", self.samples.to_string(), "at least 3");
        }
        if self.held_out < 1 || self.count < self.held_out + 1 {
            return bad(
                "count",
                format!("{} with held_out {}", self.count, self.held_out),
                "more tuples than held out (≥ 1)",
            );
        }
        if self.batch_size < 1 || self.steps < 0 || self.eval_interval < 1 {
            return bad(
                "batch_size/steps/eval_interval",
                format!("{}/{}/{}", self.batch_size, self.steps, self.eval_interval),
                "positive",
            );
        }
        if !(self.lr > 0.0 && self.lr.is_finite()) {
            return bad("lr", self.lr.to_string(), "a positive number");
        }
        for (k, v) in [("pose_weight", self.pose_weight), ("image_weight", self.image_weight)] {
            if !(v >= 0.0 && v.is_finite()) {
                return bad(k, v.to_string(), "a weight ≥ 0");
            }
        }
        if !(4..=512).contains(&self.image_resolution) {
            return bad("image_resolution", self.image_resolution.to_string(), "4 to 512");
        }
        Ok(())
    }
}

/// What the generator rendered for the initialiser to learn from.
pub struct Tuples {
    /// `(N, 3, R, R)` in [−1, 1].
    pub images: Tensor,
    /// `(N, mapping_hidden)`.
    pub w_s: Tensor,
    /// `(N, 2·L_c·H)`: the raw appearance (f, β).
    pub appearance_raw: Tensor,
    /// `(N, 2)`: pitch, yaw.
    pub poses: Tensor,
}

/// Renders `cfg.count` tuples from codes and poses drawn from `cfg.seed` (the same seed gives
/// the same tuples), `progress(done)` after each batch of 16.
pub fn generate(g: &Generator, cam: &CameraConfig, cfg: &InitConfig, progress: &mut dyn FnMut(i64)) -> Result<Tuples> {
    cfg.validate()?;
    let (kind, device) = g.kind_device();
    let n = cfg.count;
    let z = StepRng::new(cfg.seed, 0, Purpose::InitData, kind, device).normal(&[n, g.cfg.latent_dim as i64]);
    let poses = Poses::sample_from(cam, n, &mut StepRng::new(cfg.seed, 1, Purpose::InitData, kind, device));
    let rc = RenderConfig { num_steps: cfg.samples, jitter: false, ..Default::default() };
    let r = Renderer::new(g, cam, &rc)?;
    let (mut images, mut ws, mut apps) = (Vec::new(), Vec::new(), Vec::new());
    let mut i = 0;
    while i < n {
        let b = 16.min(n - i);
        let zb = z.narrow(0, i, b);
        let (img, w, a) = tch::no_grad(|| -> Result<_> {
            let lat = g.latents(&zb, &zb, None)?;
            let res = cfg.resolution;
            let noise = Noise::midpoints(b, res * res, cfg.samples as i64, device);
            let img = r.render_image(&lat, &poses.narrow(i, b), res, &noise)?.rgb;
            Ok((img, g.shape_w(&zb), g.appearance_raw(&zb)))
        })?;
        images.push(img);
        ws.push(w);
        apps.push(a);
        i += b;
        progress(i);
    }
    Ok(Tuples {
        images: Tensor::cat(&images, 0),
        w_s: Tensor::cat(&ws, 0),
        appearance_raw: Tensor::cat(&apps, 0),
        poses: poses.stacked(),
    })
}

#[derive(Debug, Clone, Serialize, Deserialize)]
struct InitHeader {
    format_version: u32,
    generator: String,
    resolution: i64,
    mapping_hidden: i64,
    step: i64,
    config: InitConfig,
}

/// F: ResNet-34 without its classifier, then a linear layer to (w_s, pitch, cos yaw, sin yaw).
pub struct Initialiser {
    pub vs: nn::VarStore,
    net: nn::FuncT<'static>,
    head: nn::Linear,
    pub mapping_hidden: i64,
    pub resolution: i64,
}

impl Initialiser {
    pub fn new(device: Device, mapping_hidden: i64, resolution: i64) -> Self {
        let vs = nn::VarStore::new(device);
        // tch's layers draw their start from libtorch's global generator.
        let (net, head) = crate::rng::with_global_generator(|| {
            let net = tch::vision::resnet::resnet34_no_final_layer(&(vs.root() / "resnet"));
            let head = nn::linear(vs.root() / "head", 512, mapping_hidden + 3, Default::default());
            (net, head)
        });
        Self { vs, net, head, mapping_hidden, resolution }
    }

    /// Draws every weight matrix and kernel again, He-uniform (U(±√(6 / fan_in))), from the
    /// counter-based generator of `seed`, and zeroes the head's bias: the same start on every
    /// run whatever else draws from libtorch's global generator meanwhile. Batch-norm scales
    /// and shifts keep their 1 and 0.
    pub fn reinitialise(&self, seed: u64) {
        let mut vars: Vec<(String, Tensor)> = self.vs.variables().into_iter().collect();
        vars.sort_by(|a, b| a.0.cmp(&b.0));
        tch::no_grad(|| {
            for (i, (name, mut v)) in vars.into_iter().enumerate() {
                let dims = v.size();
                if dims.len() >= 2 {
                    let fan_in: i64 = dims[1..].iter().product();
                    let bound = (6.0 / fan_in as f64).sqrt();
                    let u = StepRng::new(seed, i as u64, Purpose::InitWeights, Kind::Float, v.device()).uniform(&dims);
                    v.copy_(&((u * 2.0 - 1.0) * bound).to_kind(v.kind()));
                } else if name == "head.bias" {
                    let _ = v.zero_();
                }
            }
        });
    }

    /// `img: (B, 3, R, R)` in [−1, 1] at F's resolution → w_s `(B, H)` and the raw pose
    /// `(B, 3)` (pitch, cos yaw, sin yaw).
    pub fn forward_t(&self, img: &Tensor, train: bool) -> (Tensor, Tensor) {
        let out = self.head.forward_t(&self.net.forward_t(img, train), train);
        (out.narrow(1, 0, self.mapping_hidden), out.narrow(1, self.mapping_hidden, 3))
    }

    /// The prediction for one photo `(1, 3, S, S)` in [−1, 1] (resized to F's input):
    /// w_s `(1, H)` and (pitch, yaw) in radians.
    pub fn predict(&self, photo: &Tensor) -> Result<(Tensor, (f64, f64))> {
        let s = photo.size();
        if s.len() != 4 || s[0] != 1 || s[1] != 3 {
            return Err(Error::Shape(format!("the initialiser takes a (1, 3, S, S) photo, got {s:?}")));
        }
        let x = resize(&photo.to_kind(Kind::Float).to_device(self.vs.device()), self.resolution);
        let (w, p) = tch::no_grad(|| self.forward_t(&x, false));
        let v: Vec<f64> = Vec::try_from(p.get(0).to_kind(Kind::Double))?;
        Ok((w, (v[0], v[2].atan2(v[1]))))
    }

    fn save(&self, path: &Path, header: &InitHeader, adam: Option<&Adam>) -> Result<()> {
        let mut tensors: Vec<(String, Tensor)> = self.vs.variables().into_iter().collect();
        if let Some(a) = adam {
            tensors.extend(a.named_tensors("adam."));
        }
        tensors.sort_by(|a, b| a.0.cmp(&b.0));
        let json = serde_json::to_string(header)?;
        write_atomic(path, &tensors_to_bytes(&tensors, INIT_KEY, &json)?)
    }

    /// Loads an initialiser file made for the generator of identity `generator_id`.
    pub fn load(path: &Path, generator_id: &str, device: Device) -> Result<Self> {
        Ok(Self::load_with_state(path, Some(generator_id), device)?.0)
    }

    fn load_with_state(
        path: &Path,
        generator_id: Option<&str>,
        device: Device,
    ) -> Result<(Self, InitHeader, std::collections::BTreeMap<String, Tensor>)> {
        let (json, mut t) = load_tensors_with(path, INIT_KEY)?;
        let bad = |why: String| Error::Data { path: path.to_path_buf(), reason: format!("initialiser: {why}") };
        let h: InitHeader = serde_json::from_str(&json).map_err(|e| bad(format!("bad header ({e})")))?;
        if let Some(id) = generator_id {
            if h.generator != id {
                return Err(bad(format!("it was trained for generator {}, not for this one ({id})", h.generator)));
            }
        }
        // Checked before the network is built from them: a damaged header must not allocate.
        if !(16..=512).contains(&h.resolution) {
            return Err(bad(format!("resolution {} is out of range, expected 16 to 512", h.resolution)));
        }
        let head = t.get("head.weight").ok_or_else(|| bad("no tensor 'head.weight'".into()))?;
        if h.mapping_hidden < 1 || head.size() != [h.mapping_hidden.saturating_add(3), 512] {
            return Err(bad(format!(
                "'head.weight' has shape {:?}, but the header's mapping_hidden {} needs [{}, 512]",
                head.size(),
                h.mapping_hidden,
                h.mapping_hidden.saturating_add(3)
            )));
        }
        let init = Self::new(device, h.mapping_hidden, h.resolution);
        tch::no_grad(|| -> Result<()> {
            for (name, mut v) in init.vs.variables() {
                let src = t.remove(&name).ok_or_else(|| bad(format!("no tensor '{name}'")))?;
                if src.size() != v.size() {
                    return Err(bad(format!("'{name}' has shape {:?}, expected {:?}", src.size(), v.size())));
                }
                v.copy_(&src.to_kind(v.kind()).to_device(device));
            }
            Ok(())
        })?;
        let rest = t.into_iter().filter(|(k, _)| k.starts_with("adam.")).collect();
        Ok((init, h, rest))
    }
}

/// Validation errors on held-out tuples.
#[derive(Debug, Clone, Serialize)]
pub struct InitEval {
    pub step: i64,
    /// mean (F_w(I) − w_s)² on held-out tuples.
    pub w_mse: f64,
    /// The same for the mean code's w_s (what the optimisation starts from without F).
    pub mean_code_w_mse: f64,
    pub pitch_error_deg: f64,
    pub yaw_error_deg: f64,
    pub train_loss: f64,
}

fn pose_terms(raw: &Tensor, poses: &Tensor) -> Tensor {
    let p = Poses::from_stacked(poses);
    let want = Tensor::cat(&[p.pitch, p.yaw.cos(), p.yaw.sin()], 1);
    (raw - want).square().sum_dim_intlist(1, false, Kind::Float).mean(Kind::Float)
}

fn evaluate(init: &Initialiser, t: &Tuples, idx: &Tensor, mean_w: &Tensor, step: i64, train_loss: f64) -> InitEval {
    tch::no_grad(|| {
        let (mut w_err, mut p_err, mut y_err, mut n) = (0.0, 0.0, 0.0, 0.0);
        let m = idx.size()[0];
        let mut i = 0;
        while i < m {
            let b = 64.min(m - i);
            let id = idx.narrow(0, i, b);
            let (w, p) = init.forward_t(&t.images.index_select(0, &id), false);
            let want_w = t.w_s.index_select(0, &id);
            let want_p = t.poses.index_select(0, &id);
            w_err += f64::try_from((w - want_w).square().mean(Kind::Float)).unwrap_or(f64::NAN) * b as f64;
            p_err +=
                f64::try_from((p.narrow(1, 0, 1) - want_p.narrow(1, 0, 1)).abs().sum(Kind::Float)).unwrap_or(f64::NAN);
            // The yaw error wrapped to [0, π].
            let diff = p.narrow(1, 2, 1).atan2(&p.narrow(1, 1, 1)) - want_p.narrow(1, 1, 1);
            let dy = diff.sin().atan2(&diff.cos()).abs();
            y_err += f64::try_from(dy.sum(Kind::Float)).unwrap_or(f64::NAN);
            n += b as f64;
            i += b;
        }
        let want = t.w_s.index_select(0, idx);
        let mean_err = f64::try_from((want - mean_w).square().mean(Kind::Float)).unwrap_or(f64::NAN);
        InitEval {
            step,
            w_mse: w_err / n,
            mean_code_w_mse: mean_err,
            pitch_error_deg: (p_err / n).to_degrees(),
            yaw_error_deg: (y_err / n).to_degrees(),
            train_loss,
        }
    })
}

/// Trains F on `tuples` for generator `g` (identity `generator_id`), writing `out` (atomically)
/// every `eval_interval` steps and at the end; with `resume`, continues from `out`'s saved
/// step and Adam state. `progress(step, eval)` after each step (an evaluation when one ran).
#[allow(clippy::too_many_arguments)]
pub fn train(
    g: &Generator,
    cam: &CameraConfig,
    generator_id: &str,
    tuples: &Tuples,
    cfg: &InitConfig,
    out: &Path,
    resume: bool,
    progress: &mut dyn FnMut(i64, Option<&InitEval>),
) -> Result<(Initialiser, Vec<InitEval>)> {
    cfg.validate()?;
    let (_, device) = g.kind_device();
    let hidden = g.cfg.mapping_hidden_dim as i64;
    let (init, mut adam, start) = if resume {
        let (init, h, state) = Initialiser::load_with_state(out, Some(generator_id), device)?;
        // A longer run (or other validation points) may continue; anything else would not.
        let core = |c: &InitConfig| InitConfig { steps: 0, eval_interval: 1, ..c.clone() };
        if core(&h.config) != core(cfg) {
            return Err(Error::Config(format!(
                "{}: saved with other initialiser settings; resume with the same ones (only the steps may grow)",
                out.display()
            )));
        }
        let mut adam = Adam::new(&init.vs, 0.9, 0.999, 1e-8);
        adam.load(&state, "adam.", h.step)?;
        (init, adam, h.step)
    } else {
        let init = Initialiser::new(device, hidden, cfg.resolution);
        init.reinitialise(cfg.seed);
        let adam = Adam::new(&init.vs, 0.9, 0.999, 1e-8);
        (init, adam, 0)
    };
    let n_train = cfg.count - cfg.held_out;
    let held = Tensor::arange_start(n_train, cfg.count, (Kind::Int64, device));
    let mean_w = tuples.w_s.narrow(0, 0, n_train).mean_dim(0, true, Kind::Float);
    let images_small = (cfg.image_weight > 0.0).then(|| resize(&tuples.images, cfg.image_resolution));
    let rc = RenderConfig { num_steps: cfg.samples, ..Default::default() };
    let renderer = Renderer::new(g, cam, &rc)?;
    let mut evals = Vec::new();
    let mut last_loss = f64::NAN;
    for step in start..cfg.steps {
        let idx = Tensor::from_slice(
            &StepRng::new(cfg.seed, step as u64, Purpose::InitBatches, Kind::Float, device)
                .below(cfg.batch_size as usize, n_train as u64),
        )
        .to_device(device);
        let img = tuples.images.index_select(0, &idx);
        let (w, p) = init.forward_t(&img, true);
        let mut loss = (&w - tuples.w_s.index_select(0, &idx)).square().mean(Kind::Float)
            + pose_terms(&p, &tuples.poses.index_select(0, &idx)) * cfg.pose_weight;
        if let Some(small) = &images_small {
            let poses = Poses::from_stacked(&tuples.poses.index_select(0, &idx));
            let lat = Latents {
                shape: g.shape_from_w(&w, None),
                appearance: Film::from_raw(&tuples.appearance_raw.index_select(0, &idx)),
            };
            let (r2, n) = (cfg.image_resolution * cfg.image_resolution, cfg.samples as i64);
            let noise = Noise::midpoints(cfg.batch_size, r2, n, device);
            let (re, _) = renderer.render_regions(&lat, &poses, cfg.image_resolution, 1, &noise)?;
            loss += (re - small.index_select(0, &idx)).square().mean(Kind::Float) * cfg.image_weight;
        }
        last_loss = loss.double_value(&[]);
        if !last_loss.is_finite() {
            return Err(Error::Invalid(format!("the initialiser's loss is not finite at step {step}; lower init.lr")));
        }
        zero_grads(&init.vs);
        loss.backward();
        adam.step(&init.vs, cfg.lr);
        let done = step + 1;
        let ev = (done % cfg.eval_interval == 0 || done == cfg.steps).then(|| {
            let e = evaluate(&init, tuples, &held, &mean_w, done, last_loss);
            evals.push(e.clone());
            e
        });
        if ev.is_some() {
            let header = InitHeader {
                format_version: 1,
                generator: generator_id.into(),
                resolution: cfg.resolution,
                mapping_hidden: hidden,
                step: done,
                config: cfg.clone(),
            };
            init.save(out, &header, Some(&adam))?;
        }
        progress(done, ev.as_ref());
    }
    if evals.is_empty() {
        evals.push(evaluate(&init, tuples, &held, &mean_w, cfg.steps, last_loss));
    }
    Ok((init, evals))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::GeneratorConfig;

    fn small() -> (nn::VarStore, Generator) {
        tch::manual_seed(2);
        let vs = nn::VarStore::new(Device::Cpu);
        let cfg = GeneratorConfig::tiny();
        let g = Generator::new(&vs.root(), &cfg).unwrap();
        (vs, g)
    }

    fn cfg() -> InitConfig {
        InitConfig {
            resolution: 16,
            samples: 4,
            count: 12,
            held_out: 4,
            batch_size: 4,
            steps: 4,
            eval_interval: 2,
            ..Default::default()
        }
    }

    #[test]
    fn tuples_are_reproducible_and_training_resumes_exactly() {
        let (_vs, g) = small();
        let cam = CameraConfig::default();
        let t = generate(&g, &cam, &cfg(), &mut |_| {}).unwrap();
        assert_eq!(t.images.size(), [12, 3, 16, 16]);
        assert_eq!(t.w_s.size(), [12, 16]);
        assert_eq!(t.poses.size(), [12, 2]);
        assert!(t.images.equal(&generate(&g, &cam, &cfg(), &mut |_| {}).unwrap().images));

        let dir = std::env::temp_dir().join(format!("gdrf-init-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (a, b) = (dir.join("a.safetensors"), dir.join("b.safetensors"));
        let mut steps = Vec::new();
        let (full, evals) = train(&g, &cam, "gen", &t, &cfg(), &a, false, &mut |s, _| steps.push(s)).unwrap();
        assert_eq!(steps, [1, 2, 3, 4]);
        assert_eq!(evals.iter().map(|e| e.step).collect::<Vec<_>>(), [2, 4]);
        assert!(evals.iter().all(|e| e.w_mse.is_finite() && e.mean_code_w_mse > 0.0));
        // Two steps, then a resume from the file saved at step 2: the file holds exactly the
        // state at step 2 (weights, batch-norm statistics), and the resumed run continues from
        // it to step 4. (Bit-exact equality with the uninterrupted run is not promised: the
        // multithreaded CPU convolution backward is not deterministic, so two fresh runs already
        // differ in the last bits, which Adam amplifies for near-zero gradients.)
        let (part, _) =
            train(&g, &cam, "gen", &t, &InitConfig { steps: 2, ..cfg() }, &b, false, &mut |_, _| {}).unwrap();
        let (saved, h, state) = Initialiser::load_with_state(&b, None, Device::Cpu).unwrap();
        assert_eq!(h.step, 2);
        assert!(state.keys().any(|k| k.starts_with("adam.m.")), "the Adam state is saved");
        for (name, v) in part.vs.variables() {
            assert!(v.equal(&saved.vs.variables()[&name]), "{name}");
        }
        let mut resumed_steps = Vec::new();
        let (_, evals) = train(&g, &cam, "gen", &t, &cfg(), &b, true, &mut |s, _| resumed_steps.push(s)).unwrap();
        assert_eq!(resumed_steps, [3, 4]);
        assert_eq!(evals.iter().map(|e| e.step).collect::<Vec<_>>(), [4]);
        let other = InitConfig { lr: 0.5, ..cfg() };
        let e = train(&g, &cam, "gen", &t, &other, &b, true, &mut |_, _| {}).err().map(|e| e.to_string());
        assert!(e.as_deref().unwrap_or("").contains("other initialiser settings"), "{e:?}");
        // Another generator's initialiser is refused; predictions are finite.
        let err = Initialiser::load(&a, "other", Device::Cpu).err().map(|e| e.to_string()).unwrap_or_default();
        assert!(err.contains("other") && err.contains("gen"), "{err}");
        let (w, (pitch, yaw)) = full.predict(&t.images.narrow(0, 0, 1)).unwrap();
        assert_eq!(w.size(), [1, 16]);
        assert!(pitch.is_finite() && yaw.is_finite());
        assert!(full.predict(&t.images).is_err());
        std::fs::remove_dir_all(dir).ok();
    }
}
