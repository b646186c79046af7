//! The release's template, SIREN layers: the first implementation of [`super::Template`]
//! (`template = "siren"`, [`crate::config::TemplateKind::Siren`]).
//!
//! The density trunk T_σ is unconditioned (plain SIREN layers): density depends only on
//! where a point lands in template space. The colour branch T_c is FiLM-modulated by the
//! appearance code and reads the trunk feature f_t; the view direction enters only the
//! last colour layer ("deferred direction").
use super::Template;
use crate::config::GeneratorConfig;
use crate::nn::film::{Film, FilmLayer};
use crate::nn::siren::SineLayer;
use crate::nn::{Linear, WeightInit};
use tch::{nn, Kind, Tensor};

/// Parameter names are the release's (`trunk`, `sigma_head`, `color`, `rgb_head`), which
/// checkpoints carry.
#[derive(Debug)]
pub struct SirenTemplate {
    pub trunk: Vec<SineLayer>,
    pub sigma_head: Linear,
    pub colour: Vec<FilmLayer>,
    pub rgb_head: Linear,
    hidden: usize,
}

impl SirenTemplate {
    /// The layers under `vs`, with the release's initialisation.
    pub fn new(vs: nn::Path, cfg: &GeneratorConfig) -> Self {
        let h = cfg.hidden_dim;
        let trunk = (0..cfg.trunk_layers)
            .map(|i| {
                let (inp, init) = if i == 0 { (3, WeightInit::FirstLayer) } else { (h, WeightInit::Frequency(30.0)) };
                SineLayer::new(vs.clone() / "trunk" / i, inp, h, init)
            })
            .collect();
        let sigma_head = Linear::new(vs.clone() / "sigma_head", h, 1, WeightInit::Frequency(30.0));
        let last = cfg.colour_layers - 1;
        let colour = (0..cfg.colour_layers)
            .map(|i| {
                // The release gives colour layer 0 the first-layer rule U(±1/fan_in) although
                // its input is the 256-d feature; the direction is prepended to the last layer.
                let init = if i == 0 { WeightInit::FirstLayer } else { WeightInit::Frequency(25.0) };
                let inp = if i == last { h + 3 } else { h };
                // "color": the release's parameter names, which checkpoints carry.
                FilmLayer::new(vs.clone() / "color" / i, inp, h, init)
            })
            .collect();
        let rgb_head = Linear::new(vs / "rgb_head", h, 3, WeightInit::Frequency(25.0));
        Self { trunk, sigma_head, colour, rgb_head, hidden: h }
    }
}

impl Template for SirenTemplate {
    /// The trunk's first layer (3 → H) runs in the points' dtype, the rest in `kind`.
    fn density_in(&self, x_t: &Tensor, kind: Option<Kind>) -> (Tensor, Tensor) {
        let mut f = x_t.shallow_clone();
        for (i, layer) in self.trunk.iter().enumerate() {
            f = layer.forward(&f);
            if let (0, Some(k)) = (i, kind) {
                f = f.to_kind(k);
            }
        }
        let sigma = crate::nn::like(&self.sigma_head.forward(&f), x_t);
        (f, sigma)
    }

    /// `f_t: (B, P, H)`; the direction is prepended to the last colour layer's input.
    fn colour(&self, f_t: &Tensor, dirs: &Tensor, appearance: &Film) -> Tensor {
        let last = self.colour.len() - 1;
        let mut h = f_t.shallow_clone();
        for (i, layer) in self.colour.iter().enumerate() {
            if i == last {
                h = Tensor::cat(&[dirs, &h], -1);
            }
            let (g, b) = appearance.layer(i, self.hidden);
            h = layer.forward(&h, &g, &b);
        }
        self.rgb_head.forward(&h).sigmoid()
    }
}
