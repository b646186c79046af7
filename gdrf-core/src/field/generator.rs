//! The composed generator: codes or features → modulations → density first, colour second.
use super::deform::DeformField;
use super::template::{self, Template};
use crate::config::GeneratorConfig;
use crate::nn::film::Film;
use crate::nn::mapping::MappingNetwork;
use crate::{Error, Result};
use tch::{nn, Device, Kind, Tensor};

/// The modulations that drive one batch: shape (Φ) and appearance (T_c).
#[derive(Debug)]
pub struct Latents {
    pub shape: Film,
    pub appearance: Film,
}

impl Latents {
    pub fn narrow(&self, start: i64, len: i64) -> Self {
        Self { shape: self.shape.narrow(start, len), appearance: self.appearance.narrow(start, len) }
    }
    pub fn batch_size(&self) -> i64 {
        self.shape.batch_size()
    }
}

/// Codes averaged for the mean mapping output of [`Generator::truncation_at`].
pub const TRUNCATION_MEAN_CODES: i64 = 10_000;

/// Truncation toward the mean raw mapping output: raw ← mean + ψ·(raw − mean).
#[derive(Debug)]
pub struct Truncation {
    pub psi: f64,
    /// `(1, 2·L_s·H)` mean raw output of the shape mapping network.
    pub shape_mean: Tensor,
    /// `(1, 2·L_c·H)` mean raw output of the appearance mapping network.
    pub appearance_mean: Tensor,
}

/// Ablations of the inference renderer (release options `no_deformation`, `no_correct`)
/// and the arithmetic of the field's networks.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct FieldOptions {
    /// Evaluate the template at x instead of x + Δx.
    pub no_deformation: bool,
    /// Drop the density correction Δσ.
    pub no_correction: bool,
    /// Evaluate the hidden SIREN/FiLM layers in this dtype (`BFloat16` on GPUs) with
    /// float32 master weights and modulations. Positions, the cheap 3 → H first layers,
    /// Δx, σ and colours stay in the points' dtype, and the renderer integrates in float32
    /// or wider (1e10 intervals and softplus underflow need it).
    pub compute_kind: Option<Kind>,
}

/// The result of a density query at target-space points `x: (B, P, 3)`.
#[derive(Debug)]
pub struct Density {
    /// Raw final density σ_t(x + Δx) + Δσ: `(B, P, 1)`.
    pub sigma: Tensor,
    /// Template feature f_t at x + Δx: `(B, P, F)` (the trunk's, F = H, for SIREN), input
    /// of the colour query.
    pub feature: Tensor,
    /// Template density σ_t: `(B, P, 1)`.
    pub sigma_t: Tensor,
    /// Template-space points x + Δx: `(B, P, 3)`.
    pub x_template: Tensor,
    pub dx: Tensor,
    pub dsigma: Tensor,
}

#[derive(Debug)]
pub struct Generator {
    pub cfg: GeneratorConfig,
    pub shape_mapping: MappingNetwork,
    pub appearance_mapping: MappingNetwork,
    pub deform: DeformField,
    /// T, the one `cfg.template` names.
    pub template: Box<dyn Template>,
}

impl Generator {
    /// Creates the networks under `vs` with the release's initialisation (drawn from
    /// libtorch's global generator under [`crate::rng::with_global_generator`]).
    pub fn new(vs: &nn::Path, cfg: &GeneratorConfig) -> Result<Self> {
        crate::rng::with_global_generator(|| Self::create(vs, cfg))
    }

    fn create(vs: &nn::Path, cfg: &GeneratorConfig) -> Result<Self> {
        cfg.validate()?;
        let (z, h, m) = (cfg.latent_dim, cfg.hidden_dim, cfg.mapping_hidden_dim);
        Ok(Self {
            cfg: cfg.clone(),
            template: template::build(vs / "template", cfg),
            appearance_mapping: MappingNetwork::new(vs / "appearance_mapping", z, m, 2 * cfg.colour_layers * h),
            deform: DeformField::new(vs / "deform", cfg),
            shape_mapping: MappingNetwork::new(vs / "shape_mapping", z, m, 2 * cfg.deform_layers * h),
        })
    }

    /// Mean raw mapping outputs over `n` codes drawn from `seed`, for truncation ψ.
    pub fn truncation(&self, psi: f64, n: i64, seed: i64) -> Truncation {
        let w = &self.shape_mapping.layers[0].weight;
        let (kind, device) = (w.kind(), w.device());
        Truncation {
            psi,
            shape_mean: self.shape_mapping.mean_output(n, seed, kind, device),
            appearance_mean: self.appearance_mapping.mean_output(n, seed.wrapping_add(1), kind, device),
        }
    }

    /// The truncation every tool renders and scores with at ψ (gdrf-edit's, gdrf-train
    /// eval's `--psi`): the mean over [`TRUNCATION_MEAN_CODES`] codes of seed 0, so one ψ
    /// means one thing everywhere; `None` at ψ = 1 (no truncation, nothing to compute).
    pub fn truncation_at(&self, psi: f64) -> Option<Truncation> {
        (psi != 1.0).then(|| self.truncation(psi, TRUNCATION_MEAN_CODES, 0))
    }

    /// w_s: `(B, mapping_hidden)` for shape codes `z_s: (B, latent)`.
    pub fn shape_w(&self, z_s: &Tensor) -> Tensor {
        self.shape_mapping.features(z_s)
    }

    /// Shape modulation (γ_s, β_s) from w_s `(B, mapping_hidden)`.
    pub fn shape_from_w(&self, w_s: &Tensor, trunc: Option<&Truncation>) -> Film {
        let raw = self.shape_mapping.head(w_s);
        Film::from_raw(&truncate(raw, trunc.map(|t| (t.psi, &t.shape_mean))))
    }

    /// Shape modulation from z_s `(B, latent)`.
    pub fn shape_from_z(&self, z_s: &Tensor, trunc: Option<&Truncation>) -> Film {
        self.shape_from_w(&self.shape_w(z_s), trunc)
    }

    /// The appearance mapping network's raw output (f, β) `(B, 2·L_c·H)` for codes `z_a`.
    pub fn appearance_raw(&self, z_a: &Tensor) -> Tensor {
        self.appearance_mapping.forward(z_a)
    }

    /// Appearance modulation (γ_a, β_a) from z_a `(B, latent)`.
    pub fn appearance_from_z(&self, z_a: &Tensor, trunc: Option<&Truncation>) -> Film {
        let raw = self.appearance_mapping.forward(z_a);
        Film::from_raw(&truncate(raw, trunc.map(|t| (t.psi, &t.appearance_mean))))
    }

    /// Both modulations from codes `z_s, z_a: (B, latent)`. The release feeds one code to
    /// both (z_s = z_a). Codes of another shape are an error, not a panic in libtorch.
    pub fn latents(&self, z_s: &Tensor, z_a: &Tensor, trunc: Option<&Truncation>) -> Result<Latents> {
        let want = self.cfg.latent_dim as i64;
        let (s, a) = (z_s.size(), z_a.size());
        if s.len() != 2 || s[1] != want || a.len() != 2 || a[1] != want || s[0] != a[0] {
            return Err(Error::Shape(format!(
                "codes z_s {s:?} and z_a {a:?}: expected two (B, {want}) batches of the same size"
            )));
        }
        Ok(Latents { shape: self.shape_from_z(z_s, trunc), appearance: self.appearance_from_z(z_a, trunc) })
    }

    /// Density-only query (the shape side): `x: (B, P, 3)`.
    pub fn density(&self, x: &Tensor, shape: &Film, opts: FieldOptions) -> Density {
        let (dx, dsigma) = self.deform.forward_in(x, shape, opts.compute_kind);
        let x_template = if opts.no_deformation { x.shallow_clone() } else { x + &dx };
        let (feature, sigma_t) = self.template.density_in(&x_template, opts.compute_kind);
        let sigma = if opts.no_correction { sigma_t.shallow_clone() } else { &sigma_t + &dsigma };
        Density { sigma, feature, sigma_t, x_template, dx, dsigma }
    }

    /// Colour query (the appearance side): `feature: (B, P, F)`, `dirs: (B, P, 3)` → rgb
    /// `(B, P, 3)` in (0, 1).
    pub fn colour(&self, feature: &Tensor, dirs: &Tensor, appearance: &Film) -> Tensor {
        let rgb = self.template.colour(feature, &crate::nn::like(dirs, feature), appearance);
        crate::nn::like(&rgb, dirs)
    }

    /// Φ alone at target-space points `x: (B, P, 3)`: `(Δx: (B, P, 3), Δσ: (B, P, 1))`,
    /// Δσ already scaled by the correction scale.
    pub fn deformation(&self, x: &Tensor, shape: &Film) -> (Tensor, Tensor) {
        self.deform.forward(x, shape)
    }

    /// T_σ alone at template-space points `x_t: (B, P, 3)`: `(f_t: (B, P, F), σ_t: (B, P, 1))`.
    pub fn template_density(&self, x_t: &Tensor) -> (Tensor, Tensor) {
        self.template.density(x_t)
    }

    /// Full query: `(rgb: (B, P, 3), σ: (B, P, 1))`.
    pub fn forward(&self, x: &Tensor, dirs: &Tensor, latents: &Latents) -> (Tensor, Tensor) {
        let d = self.density(x, &latents.shape, FieldOptions::default());
        (self.colour(&d.feature, dirs, &latents.appearance), d.sigma)
    }

    /// Dtype and device of the parameters.
    pub fn kind_device(&self) -> (Kind, Device) {
        let w = &self.shape_mapping.layers[0].weight;
        (w.kind(), w.device())
    }
}

fn truncate(raw: Tensor, t: Option<(f64, &Tensor)>) -> Tensor {
    match t {
        Some((psi, mean)) if psi != 1.0 => mean + (raw - mean) * psi,
        _ => raw,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn count(vs: &nn::VarStore) -> i64 {
        vs.trainable_variables().iter().map(|t| t.numel() as i64).sum()
    }

    #[test]
    fn parameter_counts_match_the_release() {
        let vs = nn::VarStore::new(Device::Cpu);
        let g = Generator::new(&vs.root(), &GeneratorConfig::default()).unwrap();
        assert_eq!(count(&vs), 2_176_008);
        assert_eq!(vs.variables().len(), 48);
        let _ = g;
    }

    #[test]
    fn initial_deformation_is_constant_and_jacobian_zero() {
        tch::manual_seed(1);
        let vs = nn::VarStore::new(Device::Cpu);
        let g = Generator::new(&vs.root(), &GeneratorConfig::default()).unwrap();
        let z = Tensor::randn([2, 256], (Kind::Float, Device::Cpu));
        let shape = g.shape_from_z(&z, None);
        let x = (Tensor::rand([2, 50, 3], (Kind::Float, Device::Cpu)) - 0.5).set_requires_grad(true);
        let (dx, dsigma) = g.deform.forward(&x, &shape);
        // Δx equals the head bias everywhere; Δσ = 100 · bias.
        let bias = g.deform.head.bias.detach();
        let want_dx = bias.narrow(0, 0, 3).view([1, 1, 3]).expand_as(&dx);
        assert_eq!(f64::try_from((&dx - want_dx).abs().max()).unwrap(), 0.0);
        let want_ds = bias.narrow(0, 3, 1) * 100.0;
        assert!(f64::try_from((&dsigma - want_ds).abs().max()).unwrap() < 1e-5);
        let grad = Tensor::run_backward(&[dx.sum(Kind::Float)], &[&x], false, false);
        assert_eq!(f64::try_from(grad[0].abs().max()).unwrap(), 0.0);
    }

    /// The count a config promises without building (what checkpoint loading compares with
    /// the file) is the built generator's, for the default, the tiny and odd configs.
    #[test]
    fn parameter_count_is_the_built_generators() {
        for cfg in [
            GeneratorConfig::default(),
            GeneratorConfig::tiny(),
            GeneratorConfig {
                latent_dim: 5,
                hidden_dim: 7,
                mapping_hidden_dim: 11,
                trunk_layers: 1,
                colour_layers: 2,
                deform_layers: 3,
                ..Default::default()
            },
        ] {
            let vs = nn::VarStore::new(Device::Cpu);
            Generator::new(&vs.root(), &cfg).unwrap();
            let built: i64 = vs.variables().values().map(|t| t.numel() as i64).sum();
            assert_eq!(cfg.parameter_count(), built as u128, "{cfg:?}");
        }
        for huge in [
            GeneratorConfig { hidden_dim: usize::MAX, ..Default::default() },
            GeneratorConfig { hidden_dim: usize::MAX, colour_layers: usize::MAX, ..Default::default() },
        ] {
            assert_eq!(huge.parameter_count(), u128::MAX);
        }
    }

    /// With a non-zero head (`deform_head_frequency`), codes start with different shapes:
    /// Δx at the same points differs between two codes, by about the head's scale.
    #[test]
    fn a_frequency_initialised_head_gives_each_code_its_shape() {
        let vs = nn::VarStore::new(Device::Cpu);
        let cfg = GeneratorConfig { hidden_dim: 64, deform_head_frequency: 50.0, ..Default::default() };
        let g = Generator::new(&vs.root(), &cfg).unwrap();
        // The Δσ row stays zero (Δσ is scaled by 100): every code starts with the same Δσ.
        assert_eq!(f64::try_from(g.deform.head.weight.get(3).abs().max()).unwrap(), 0.0);
        let w = g.deform.head.weight.narrow(0, 0, 3).detach();
        let bound = (6.0f64 / 64.0).sqrt() / 50.0;
        assert!(f64::try_from(w.abs().max()).unwrap() <= bound);
        assert!(f64::try_from(w.abs().max()).unwrap() > 0.5 * bound);
        let z = Tensor::randn([2, 256], (Kind::Float, Device::Cpu));
        let x = Tensor::rand([1, 50, 3], (Kind::Float, Device::Cpu)).expand([2, 50, 3], false) - 0.5;
        let (dx, dsigma) = g.deform.forward(&x, &g.shape_from_z(&z, None));
        assert_eq!(f64::try_from((dsigma.get(0) - dsigma.get(1)).abs().max()).unwrap(), 0.0);
        let diff = f64::try_from((dx.get(0) - dx.get(1)).abs().mean(Kind::Float)).unwrap();
        println!("mean |Δx(z₀) − Δx(z₁)| = {diff:.2e}");
        assert!(diff > 1e-3 && diff < 0.1, "mean |Δx(z₀) − Δx(z₁)| = {diff}");
        let bad = GeneratorConfig { deform_head_frequency: -1.0, ..Default::default() }.validate();
        assert!(bad.unwrap_err().to_string().contains("deform_head_frequency"));
    }

    /// Codes of the wrong width, rank or batch are a shape error naming both shapes.
    #[test]
    fn codes_of_the_wrong_shape_are_an_error() {
        let vs = nn::VarStore::new(Device::Cpu);
        let g = Generator::new(&vs.root(), &GeneratorConfig::tiny()).unwrap();
        let l = g.cfg.latent_dim as i64;
        let z = |s: &[i64]| Tensor::zeros(s, (Kind::Float, Device::Cpu));
        assert_eq!(g.latents(&z(&[3, l]), &z(&[3, l]), None).unwrap().batch_size(), 3);
        for (s, a) in [(vec![3, l + 1], vec![3, l]), (vec![3, l], vec![l]), (vec![3, l], vec![2, l])] {
            let e = g.latents(&z(&s), &z(&a), None).unwrap_err();
            assert!(matches!(e, crate::Error::Shape(_)), "{e}");
            assert!(e.to_string().contains(&format!("{s:?}")) && e.to_string().contains(&format!("{a:?}")), "{e}");
        }
    }

    #[test]
    fn truncation_zero_gives_the_mean_modulation() {
        let vs = nn::VarStore::new(Device::Cpu);
        let g = Generator::new(&vs.root(), &GeneratorConfig::default()).unwrap();
        let t = g.truncation(0.0, 1000, 3);
        let z = Tensor::randn([3, 256], (Kind::Float, Device::Cpu));
        let a = g.appearance_from_z(&z, Some(&t));
        let m = Film::from_raw(&t.appearance_mean);
        let d = (a.gamma - m.gamma).abs().max();
        assert!(f64::try_from(d).unwrap() < 1e-4);
    }
}
