//! The radiance field: deformation/correction Φ (shape side), template T (density T_σ,
//! colour T_c; the [`template::Template`] trait, the release's SIREN its first
//! implementation) and their composition in the generator.
pub mod deform;
pub mod generator;
pub mod template;

use crate::nn::film::Film;
use generator::FieldOptions;
use tch::{Device, Kind, Tensor};

/// What the renderer queries: density first, returning the feature that colour needs,
/// then colour from that feature. The generator is one; an analytic scene with exact
/// surfaces (the benchmark's and the tests' ground truth) is another.
pub trait RadianceField {
    /// Raw density σ `(B, P, 1)` (the renderer applies softplus) and the colour feature
    /// `(B, P, F)` at points `x: (B, P, 3)`, for shape modulation `shape` (one row per image).
    fn sigma_feature(&self, x: &Tensor, shape: &Film, opts: FieldOptions) -> (Tensor, Tensor);
    /// Colours `(B, P, 3)` in (0, 1) from features `(B, P, F)` and view directions `(B, P, 3)`.
    fn radiance(&self, feature: &Tensor, dirs: &Tensor, appearance: &Film) -> Tensor;
    /// Dtype and device of the queries.
    fn kind_device(&self) -> (Kind, Device);
    /// Whether the field colours each ray's last sample (the background); when not, renders
    /// paint it white ([`crate::config::Background`]).
    fn paints_background(&self) -> bool {
        true
    }
}

impl RadianceField for generator::Generator {
    fn sigma_feature(&self, x: &Tensor, shape: &Film, opts: FieldOptions) -> (Tensor, Tensor) {
        let d = self.density(x, shape, opts);
        (d.sigma, d.feature)
    }
    fn radiance(&self, feature: &Tensor, dirs: &Tensor, appearance: &Film) -> Tensor {
        self.colour(feature, dirs, appearance)
    }
    fn kind_device(&self) -> (Kind, Device) {
        generator::Generator::kind_device(self)
    }
    fn paints_background(&self) -> bool {
        self.cfg.background.is_learned()
    }
}
