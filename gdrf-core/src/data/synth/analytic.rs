//! A procedural object as a radiance field with exact surfaces: density
//! `peak · sigmoid(−sdf / width)` from the scene's signed distance, colour the albedo of
//! the nearest part (no lighting). It has what the renderer's shortcuts exploit — empty
//! space and sharp surfaces — and, unlike a trained model, a ground truth; the renderer
//! benchmark and tests use it beside the shipped generator.
use super::material::Appearance;
use super::render::{fit_radius, Scene};
use super::sdf::v3;
use super::ShapeParams;
use crate::config::CameraConfig;
use crate::data::par_try_map;
use crate::field::generator::FieldOptions;
use crate::field::RadianceField;
use crate::nn::film::Film;
use crate::{Latents, Result};
use tch::{Device, Kind, Tensor};

#[derive(Debug, Clone)]
pub struct AnalyticField {
    scene: Scene,
    /// Density deep inside the object.
    pub peak: f64,
    /// Width of the density's transition across the surface, in world units.
    pub width: f64,
}

impl AnalyticField {
    /// The object scaled to fit `camera` as the dataset renders it, with a surface as thin
    /// as `width` and density `peak` inside.
    pub fn new(
        shape: &ShapeParams,
        appearance: &Appearance,
        camera: &CameraConfig,
        peak: f64,
        width: f64,
    ) -> Result<Self> {
        if !(peak > 0.0 && peak.is_finite() && width > 0.0 && width.is_finite()) {
            return Err(crate::Error::Invalid(format!(
                "analytic field peak {peak} and width {width}: expected positive finite numbers"
            )));
        }
        Ok(Self { scene: Scene::new(&shape.geometry(), appearance, fit_radius(camera))?, peak, width })
    }

    /// Placeholder modulations for `b` images: the field has one shape and one appearance.
    pub fn latents(&self, b: i64) -> Latents {
        let film = || Film::from_raw(&Tensor::zeros([b, 2], (Kind::Float, Device::Cpu)));
        Latents { shape: film(), appearance: film() }
    }

    /// Raw density (softplus⁻¹ of the density, floored at −80) for a signed distance.
    fn raw_sigma(&self, sdf: f32) -> f32 {
        let density = self.peak / (1.0 + (sdf as f64 / self.width).exp());
        let raw = if density > 20.0 { density } else { density.exp_m1().ln() };
        raw.max(-80.0) as f32
    }
}

impl RadianceField for AnalyticField {
    fn sigma_feature(&self, x: &Tensor, _shape: &Film, _opts: FieldOptions) -> (Tensor, Tensor) {
        let (kind, device) = (x.kind(), x.device());
        let lead: Vec<i64> = x.size()[..x.dim() - 1].to_vec();
        let p = Vec::<f32>::try_from(x.to_kind(Kind::Float).contiguous().view([-1])).expect("float points");
        let n = p.len() / 3;
        const CHUNK: usize = 4096;
        let parts = par_try_map(n.div_ceil(CHUNK), 0, |c| {
            let range = c * CHUNK..((c + 1) * CHUNK).min(n);
            Ok(range
                .map(|i| {
                    let (d, a) = self.scene.sdf_albedo(v3(p[3 * i], p[3 * i + 1], p[3 * i + 2]));
                    (self.raw_sigma(d), a)
                })
                .collect::<Vec<_>>())
        })
        .expect("no errors in the map");
        let flat: Vec<(f32, [f32; 3])> = parts.into_iter().flatten().collect();
        let sigma: Vec<f32> = flat.iter().map(|v| v.0).collect();
        let rgb: Vec<f32> = flat.iter().flat_map(|v| v.1).collect();
        let shape = |c: i64| lead.iter().copied().chain([c]).collect::<Vec<_>>();
        let t = |v: Vec<f32>, c: i64| Tensor::from_slice(&v).view(shape(c).as_slice()).to_kind(kind).to_device(device);
        (t(sigma, 1), t(rgb, 3))
    }

    fn radiance(&self, feature: &Tensor, _dirs: &Tensor, _appearance: &Film) -> Tensor {
        feature.shallow_clone()
    }

    fn kind_device(&self) -> (Kind, Device) {
        (Kind::Float, Device::Cpu)
    }
}

#[cfg(test)]
mod tests {
    use super::super::{sample_object, Category};
    use super::*;

    #[test]
    fn density_is_peak_inside_half_on_the_surface_and_empty_outside() {
        let cam = CameraConfig::chair();
        let (shape, app) = sample_object(Category::Chairs, 3);
        let f = AnalyticField::new(&shape, &app, &cam, 500.0, 0.004).unwrap();
        let softplus = |raw: f32| (raw as f64).exp().ln_1p();
        assert!((softplus(f.raw_sigma(-1.0)) - 500.0).abs() < 1e-3);
        assert!((softplus(f.raw_sigma(0.0)) - 250.0).abs() < 1e-3);
        assert!(softplus(f.raw_sigma(0.5)) < 1e-30);
        // Far from the object (a corner of the camera's cube): empty; features are albedos.
        let x = Tensor::from_slice(&[0.9f32, 0.9, 0.9, 0.0, 0.0, 0.0]).view([1, 2, 3]);
        let (sigma, rgb) = f.sigma_feature(&x, &f.latents(1).shape, FieldOptions::default());
        assert_eq!(sigma.size(), [1, 2, 1]);
        assert!(f64::try_from(sigma.get(0).get(0).get(0)).unwrap() <= -79.0);
        assert!(bool::try_from(rgb.ge(0.0).logical_and(&rgb.le(1.0)).all()).unwrap());
        assert!(AnalyticField::new(&shape, &app, &cam, 0.0, 0.004).is_err());
    }
}
