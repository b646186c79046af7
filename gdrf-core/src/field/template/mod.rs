//! T: the template radiance field shared by every instance, behind the [`Template`] trait.
//!
//! The generator asks two things of a template, in the renderer's order: density and the
//! colour feature at template-space points (the shape side, after Φ has moved them), then
//! colour from that feature under the appearance modulation. What a template is inside
//! (SIREN layers today; a voxel grid or tri-plane later) stays behind the trait.
//!
//! A new template goes in its own file beside [`siren`] (e.g. `triplane.rs`), implementing
//! [`Template`] with its parameters under `template.`. A variant of [`TemplateKind`] names it
//! in configs and checkpoint headers (`[generator] template = "triplane"`); the matches on
//! that enum are exhaustive, so the compiler then points at the three places that need an
//! arm: [`build`] here, `GeneratorConfig::parameter_count` (how many values it holds, which
//! loading checks a file's header against) and `edit::generator_id`'s config (the full
//! config for every template but SIREN).
pub mod siren;

use crate::config::{GeneratorConfig, TemplateKind};
use crate::nn::film::Film;
pub use siren::SirenTemplate;
use tch::{nn, Kind, Tensor};

/// What the generator needs of the template. The generator holds it as a `Box<dyn Template>`
/// rather than a type parameter, so that its type, and those of everything that holds one
/// (renderer, trainer, tools), stays the same whichever template a checkpoint names. The cost
/// is one dynamic call per query of a whole layer stack (a chunk of up to millions of
/// points), nothing beside its matmuls.
pub trait Template: std::fmt::Debug + Send {
    /// Density query with the hidden layers evaluated in `kind` (`None`: the points' dtype).
    /// `x_t: (B, P, 3)` template-space points → `(f_t: (B, P, F), σ_t: (B, P, 1))`: the
    /// colour feature f_t in `kind` (the colour query's input), σ_t raw (softplus is applied
    /// when integrating) in `x_t`'s dtype.
    fn density_in(&self, x_t: &Tensor, kind: Option<Kind>) -> (Tensor, Tensor);

    /// [`Self::density_in`] in the points' dtype.
    fn density(&self, x_t: &Tensor) -> (Tensor, Tensor) {
        self.density_in(x_t, None)
    }

    /// Colour query. `f_t: (B, P, F)` from [`Self::density_in`], view directions
    /// `dirs: (B, P, 3)` in f_t's dtype, and the appearance modulation (γ_a, β_a) of
    /// `color_layers` layers of width H (the appearance mapping network's output) → rgb
    /// `(B, P, 3)` in (0, 1).
    fn colour(&self, f_t: &Tensor, dirs: &Tensor, appearance: &Film) -> Tensor;
}

/// Creates the template `cfg.template` names, its parameters under `vs`, with its release
/// initialisation drawn from libtorch's global generator.
pub fn build(vs: nn::Path, cfg: &GeneratorConfig) -> Box<dyn Template> {
    match cfg.template {
        TemplateKind::Siren => Box::new(SirenTemplate::new(vs, cfg)),
    }
}
