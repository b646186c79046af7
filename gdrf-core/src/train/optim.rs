//! Adam and the generator's EMA with their state as named tensors, so a checkpoint holds
//! everything a resumed run needs (tch's optimiser does not expose its moment buffers).
use crate::{Error, Result};
use std::collections::BTreeMap;
use tch::{nn, Tensor};

/// Adam as `torch.optim.Adam` computes it (bias-corrected, eps outside the square root,
/// no weight decay) over named tensors: the trainable variables of a VarStore (training,
/// the initialiser), or a few free tensors (inversion's features and pose).
#[derive(Debug)]
pub struct Adam {
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    /// Updates taken so far (the bias-correction exponent).
    pub t: i64,
    /// First and second moments by variable name.
    pub m: BTreeMap<String, Tensor>,
    pub v: BTreeMap<String, Tensor>,
}

impl Adam {
    /// Zero moments for every variable of `vs`.
    pub fn new(vs: &nn::VarStore, beta1: f64, beta2: f64, eps: f64) -> Self {
        Self::for_tensors(vs.variables(), beta1, beta2, eps)
    }

    /// Zero moments for each named tensor of `params`.
    pub fn for_tensors(params: impl IntoIterator<Item = (String, Tensor)>, beta1: f64, beta2: f64, eps: f64) -> Self {
        let params: Vec<(String, Tensor)> = params.into_iter().collect();
        let zeros = || params.iter().map(|(n, t)| (n.clone(), t.zeros_like().detach())).collect::<BTreeMap<_, _>>();
        Self { beta1, beta2, eps, t: 0, m: zeros(), v: zeros() }
    }

    /// One update of every variable of `vs` that has a gradient, with learning rate `lr`.
    pub fn step(&mut self, vs: &nn::VarStore, lr: f64) {
        self.step_tensors(vs.variables(), lr)
    }

    /// One update of every tensor of `params` (named as at construction) that has a
    /// gradient, with learning rate `lr`.
    pub fn step_tensors(&mut self, params: impl IntoIterator<Item = (String, Tensor)>, lr: f64) {
        self.t += 1;
        let bc1 = 1.0 - self.beta1.powi(self.t as i32);
        let bc2 = 1.0 - self.beta2.powi(self.t as i32);
        tch::no_grad(|| {
            for (name, mut p) in params {
                let g = p.grad();
                if !g.defined() {
                    continue;
                }
                let (m, v) = (self.m.get_mut(&name).expect("moment"), self.v.get_mut(&name).expect("moment"));
                let _ = m.g_mul_scalar_(self.beta1).g_add_(&(&g * (1.0 - self.beta1)));
                let _ = v.g_mul_scalar_(self.beta2).g_add_(&(g.square() * (1.0 - self.beta2)));
                let denom = v.sqrt() / bc2.sqrt() + self.eps;
                let _ = p.g_sub_(&(&*m / &denom * (lr / bc1)));
            }
        });
    }

    /// The moments as named tensors under `prefix` (`{prefix}m.{name}`, `{prefix}v.{name}`).
    pub fn named_tensors(&self, prefix: &str) -> Vec<(String, Tensor)> {
        let m = self.m.iter().map(|(n, t)| (format!("{prefix}m.{n}"), t.shallow_clone()));
        let v = self.v.iter().map(|(n, t)| (format!("{prefix}v.{n}"), t.shallow_clone()));
        m.chain(v).collect()
    }

    /// Restores the moments from `tensors` (every one must be present with its shape).
    pub fn load(&mut self, tensors: &BTreeMap<String, Tensor>, prefix: &str, t: i64) -> Result<()> {
        for (kind, map) in [("m", &mut self.m), ("v", &mut self.v)] {
            for (name, dst) in map.iter_mut() {
                let key = format!("{prefix}{kind}.{name}");
                let src = tensors
                    .get(&key)
                    .ok_or_else(|| Error::Invalid(format!("checkpoint lacks the optimiser tensor '{key}'")))?;
                if src.size() != dst.size() {
                    return Err(Error::Invalid(format!(
                        "optimiser tensor '{key}' has shape {:?}, expected {:?}",
                        src.size(),
                        dst.size()
                    )));
                }
                tch::no_grad(|| dst.copy_(&src.to_kind(dst.kind()).to_device(dst.device())));
            }
        }
        self.t = t;
        Ok(())
    }
}

/// An exponential moving average of a VarStore's variables (torch_ema's rule):
/// shadow ← shadow − (1 − d)(shadow − param), d = min(decay, (1 + n)/(10 + n)) at the n-th
/// update when warming up.
#[derive(Debug, Clone, Copy)]
pub struct Ema {
    pub decay: f64,
    pub warmup: bool,
    pub updates: i64,
}

impl Ema {
    /// The decay used by the next update.
    pub fn next_decay(&self) -> f64 {
        let n = (self.updates + 1) as f64;
        if self.warmup {
            self.decay.min((1.0 + n) / (10.0 + n))
        } else {
            self.decay
        }
    }

    /// Moves `shadow`'s variables toward `live`'s (same names and shapes).
    pub fn update(&mut self, shadow: &nn::VarStore, live: &nn::VarStore) {
        let d = self.next_decay();
        self.updates += 1;
        let live = live.variables();
        tch::no_grad(|| {
            for (name, mut s) in shadow.variables() {
                let p = &live[&name];
                let _ = s.g_sub_(&((&s - p) * (1.0 - d)));
            }
        });
    }
}

/// Copies every variable of `src` into `dst` (same names and shapes).
pub fn copy_vars(dst: &nn::VarStore, src: &nn::VarStore) {
    let src = src.variables();
    tch::no_grad(|| {
        for (name, mut d) in dst.variables() {
            d.copy_(&src[&name]);
        }
    });
}

/// The global L2 norm of the gradients of `vs` (0 when none has a gradient).
pub fn grad_norm(vs: &nn::VarStore) -> f64 {
    let sq: f64 = vs
        .trainable_variables()
        .iter()
        .map(|p| p.grad())
        .filter(|g| g.defined())
        .map(|g| g.to_kind(tch::Kind::Double).square().sum(tch::Kind::Double).double_value(&[]))
        .sum();
    sq.sqrt()
}

/// Scales the gradients so that their global norm is at most `max_norm`
/// (`torch.nn.utils.clip_grad_norm_`: factor max_norm / (norm + 1e-6), capped at 1).
pub fn clip_grads(vs: &nn::VarStore, norm: f64, max_norm: f64) {
    let coef = max_norm / (norm + 1e-6);
    if coef < 1.0 {
        tch::no_grad(|| {
            for p in vs.trainable_variables() {
                let mut g = p.grad();
                if g.defined() {
                    let _ = g.g_mul_scalar_(coef);
                }
            }
        });
    }
}

/// Drops every gradient of `vs`.
pub fn zero_grads(vs: &nn::VarStore) {
    for mut p in vs.trainable_variables() {
        if p.grad().defined() {
            p.zero_grad();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::{Device, Kind};

    #[test]
    fn adam_matches_the_closed_form_of_its_first_steps() {
        let vs = nn::VarStore::new(Device::Cpu);
        let p = vs.root().var("p", &[2], nn::Init::Const(1.0));
        let mut adam = Adam::new(&vs, 0.0, 0.9, 1e-8);
        // β1 = 0: m = g; v1 = 0.1 g²; update = lr · g / (√(v1/(1−0.9)) + eps) = lr·sign(g).
        let g = Tensor::from_slice(&[0.5f32, -2.0]);
        (&p * &g).sum(Kind::Float).backward();
        adam.step(&vs, 0.1);
        let got = Vec::<f32>::try_from(&p.detach()).unwrap();
        assert!((got[0] - 0.9).abs() < 1e-6 && (got[1] - 1.1).abs() < 1e-6, "{got:?}");
        assert_eq!(adam.t, 1);
        let named = adam.named_tensors("adam.");
        assert_eq!(named.len(), 2);
        let mut back = Adam::new(&vs, 0.0, 0.9, 1e-8);
        back.load(&named.into_iter().collect(), "adam.", 1).unwrap();
        assert!(back.v["p"].equal(&adam.v["p"]));
        assert!(back.load(&BTreeMap::new(), "adam.", 1).unwrap_err().to_string().contains("adam.m.p"));
    }

    #[test]
    fn ema_warms_up_like_torch_ema() {
        let live = nn::VarStore::new(Device::Cpu);
        let mut p = live.root().var("w", &[1], nn::Init::Const(0.0));
        let shadow = nn::VarStore::new(Device::Cpu);
        let s = shadow.root().var("w", &[1], nn::Init::Const(0.0));
        let mut ema = Ema { decay: 0.999, warmup: true, updates: 0 };
        assert!((ema.next_decay() - 2.0 / 11.0).abs() < 1e-15);
        let _ = tch::no_grad(|| p.fill_(1.0));
        ema.update(&shadow, &live);
        // shadow = 0 − (1 − 2/11)(0 − 1) = 9/11.
        assert!((s.double_value(&[0]) - 9.0 / 11.0).abs() < 1e-7);
        ema.update(&shadow, &live);
        let d2 = 3.0 / 12.0;
        assert!((s.double_value(&[0]) - (9.0 / 11.0 + (1.0 - d2) * (1.0 - 9.0 / 11.0))).abs() < 1e-7);
        let late = Ema { decay: 0.999, warmup: true, updates: 100_000 };
        assert_eq!(late.next_decay(), 0.999);
    }

    #[test]
    fn clipping_scales_to_the_norm() {
        let vs = nn::VarStore::new(Device::Cpu);
        let p = vs.root().var("p", &[2], nn::Init::Const(0.0));
        (&p * Tensor::from_slice(&[3.0f32, 4.0])).sum(Kind::Float).backward();
        let n = grad_norm(&vs);
        assert!((n - 5.0).abs() < 1e-12);
        clip_grads(&vs, n, 0.5);
        assert!((grad_norm(&vs) - 0.5).abs() < 1e-6);
    }
}
