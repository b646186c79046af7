//! Φ: the deformation + correction field, a FiLM-SIREN driven by the shape modulation.
use crate::config::{GeneratorConfig, HeadBias};
use crate::nn::film::{Film, FilmLayer};
use crate::nn::{Linear, WeightInit};
use tch::{nn, Kind, Tensor};

#[derive(Debug)]
pub struct DeformField {
    pub film: Vec<FilmLayer>,
    /// 256 → 4: Δx (3) and raw Δσ (1). Zero weight at init, so Δx starts constant and
    /// ∂Δx/∂x is exactly zero (with `deform_head_frequency`, only the Δσ row is zero); the
    /// bias as `deform_head_bias` says.
    pub head: Linear,
    hidden: usize,
    correct_scale: f64,
    deform_scale: f64,
}

impl DeformField {
    pub fn new(vs: nn::Path, cfg: &GeneratorConfig) -> Self {
        let h = cfg.hidden_dim;
        let film = (0..cfg.deform_layers)
            .map(|i| {
                let (inp, init) = if i == 0 { (3, WeightInit::FirstLayer) } else { (h, WeightInit::Frequency(25.0)) };
                FilmLayer::new(vs.clone() / "film" / i, inp, h, init)
            })
            .collect();
        let init = if cfg.deform_head_frequency > 0.0 {
            WeightInit::Frequency(cfg.deform_head_frequency)
        } else {
            WeightInit::Zeros
        };
        let mut head = Linear::new(vs / "head", h, 4, init);
        tch::no_grad(|| {
            if cfg.deform_head_frequency > 0.0 {
                // Only the Δx rows start non-zero: the Δσ row is scaled by `correct_scale`
                // (100), and at f = 50 a random Δσ row filled the volume with grey fog.
                let _ = head.weight.narrow(0, 3, 1).zero_();
            }
            // Zeroed after the draw, so every other initial weight is the same either way.
            if cfg.deform_head_bias == HeadBias::Zero {
                let _ = head.bias.zero_();
            }
        });
        Self { film, head, hidden: h, correct_scale: cfg.correct_scale, deform_scale: cfg.deform_scale }
    }

    /// `x: (B, P, 3)` target-space points → `(Δx: (B, P, 3), Δσ: (B, P, 1))`, Δσ already
    /// multiplied by the correction scale.
    pub fn forward(&self, x: &Tensor, shape: &Film) -> (Tensor, Tensor) {
        self.forward_in(x, shape, None)
    }

    /// [`Self::forward`] with the hidden layers evaluated in `kind` (the first layer and
    /// the outputs stay in `x`'s dtype).
    pub fn forward_in(&self, x: &Tensor, shape: &Film, kind: Option<Kind>) -> (Tensor, Tensor) {
        let mut h = x.shallow_clone();
        for (i, layer) in self.film.iter().enumerate() {
            let (g, b) = shape.layer(i, self.hidden);
            h = layer.forward(&h, &g, &b);
            if let (0, Some(k)) = (i, kind) {
                h = h.to_kind(k);
            }
        }
        let out = crate::nn::like(&self.head.forward(&h), x);
        let raw = out.narrow(-1, 0, 3);
        let dx = if self.deform_scale == 1.0 { raw } else { raw * self.deform_scale };
        (dx, out.narrow(-1, 3, 1) * self.correct_scale)
    }
}
