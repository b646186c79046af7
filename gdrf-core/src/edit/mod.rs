//! Editing's inputs: where a shape and an appearance come from (a latent seed, a feature
//! file, a photo), the feature file that gdrf-invert writes and gdrf-edit reads, and the
//! generator identity that ties one to the other.
//!
//! A feature file holds one source's **shape** as w_s `(1, mapping_hidden)` (the shape
//! mapping network's features before its head, which inversion optimises) and its
//! **appearance** as the colour branch's modulation γ_a, β_a `(1, L_c·H)` each, optionally a
//! pose, and the identity of the generator it was made with. It is a safetensors file with
//! the JSON header under the metadata key `gdrf_features`.
pub mod matrix;
pub mod view;

use crate::checkpoint::{load_tensors_with, tensors_to_bytes};
use crate::config::{GeneratorConfig, TemplateKind};
use crate::field::generator::{Generator, Truncation};
use crate::nn::film::Film;
use crate::nn::mapping::seeded_randn;
use crate::paths::write_atomic;
use crate::{Error, Latents, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use tch::{nn, Device, Kind, Tensor};

/// Metadata key of a feature file's JSON header.
pub const FEATURES_KEY: &str = "gdrf_features";

/// Where a shape or an appearance comes from.
#[derive(Debug, Clone, PartialEq)]
pub enum Source {
    /// `seed:N`: the code z = randn(1, latent) after manual_seed(N), as `render --seeds`.
    Seed(i64),
    /// A feature file (`.safetensors`) written by gdrf-invert or `gdrf-edit features`.
    Features(PathBuf),
    /// A photo (`.png`, `.jpg`, `.jpeg`), to be inverted.
    Image(PathBuf),
}

impl std::str::FromStr for Source {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        let bad = |why: &str| {
            Error::Invalid(format!(
                "source '{s}': {why}; expected seed:N, a feature file (.safetensors) or an image (.png, .jpg)"
            ))
        };
        if let Some(n) = s.strip_prefix("seed:") {
            return n.trim().parse().map(Source::Seed).map_err(|_| bad("the seed is not an integer"));
        }
        let path = PathBuf::from(s);
        let ext = path.extension().map(|e| e.to_string_lossy().to_ascii_lowercase()).unwrap_or_default();
        let source = match ext.as_str() {
            "safetensors" => Source::Features(path.clone()),
            "png" | "jpg" | "jpeg" => Source::Image(path.clone()),
            _ => return Err(bad("unknown kind of source")),
        };
        if !path.is_file() {
            return Err(Error::Invalid(format!("source '{s}': no such file")));
        }
        Ok(source)
    }
}

/// One source's shape and appearance features.
#[derive(Debug)]
pub struct Features {
    /// `(1, mapping_hidden)`.
    pub w_s: Tensor,
    /// `(1, L_c·H)` each.
    pub appearance: Film,
    /// (pitch, yaw) in radians, where the source was seen (inversion estimates it).
    pub pose: Option<(f64, f64)>,
    /// `(1, latent)`: the code, for sources that have one (seeds); interpolation slerps it.
    pub z: Option<Tensor>,
}

#[derive(Debug, Serialize, Deserialize)]
struct FeaturesHeader {
    format_version: u32,
    generator: String,
    pose: Option<(f64, f64)>,
}

impl Features {
    /// The features of latent seed `seed` (one code for shape and appearance, as in training).
    pub fn from_seed(g: &Generator, seed: i64) -> Self {
        let (kind, device) = g.kind_device();
        let z = seeded_randn(&[1, g.cfg.latent_dim as i64], seed).to_kind(kind).to_device(device);
        tch::no_grad(|| Self { w_s: g.shape_w(&z), appearance: g.appearance_from_z(&z, None), pose: None, z: Some(z) })
    }

    /// Writes the features atomically, tied to generator identity `generator_id`.
    pub fn save(&self, path: &Path, generator_id: &str) -> Result<()> {
        write_atomic(path, &self.to_bytes(generator_id)?)
    }

    /// The feature file's bytes ([`Self::save`] writes them).
    pub fn to_bytes(&self, generator_id: &str) -> Result<Vec<u8>> {
        let header = FeaturesHeader { format_version: 1, generator: generator_id.to_string(), pose: self.pose };
        let tensors = vec![
            ("w_s".to_string(), self.w_s.shallow_clone()),
            ("gamma_a".to_string(), self.appearance.gamma.shallow_clone()),
            ("beta_a".to_string(), self.appearance.beta.shallow_clone()),
        ];
        let json = serde_json::to_string(&header).map_err(|e| Error::Invalid(e.to_string()))?;
        tensors_to_bytes(&tensors, FEATURES_KEY, &json)
    }

    /// The same features, their tensors shared (a cache hands them out without copying).
    pub fn shallow_clone(&self) -> Self {
        Self {
            w_s: self.w_s.shallow_clone(),
            appearance: Film {
                gamma: self.appearance.gamma.shallow_clone(),
                beta: self.appearance.beta.shallow_clone(),
            },
            pose: self.pose,
            z: self.z.as_ref().map(Tensor::shallow_clone),
        }
    }

    /// Reads a feature file made for generator `g` (identity `generator_id`): another
    /// generator's file, or tensors of the wrong shape, are errors that name the file.
    pub fn load(path: &Path, g: &Generator, generator_id: &str) -> Result<Self> {
        let (json, mut t) = load_tensors_with(path, FEATURES_KEY)?;
        let bad = |why: String| Error::Invalid(format!("feature file {}: {why}", path.display()));
        let header: FeaturesHeader = serde_json::from_str(&json).map_err(|e| bad(format!("bad header ({e})")))?;
        if header.generator != generator_id {
            return Err(bad(format!(
                "it was made with generator {}, not with this one ({generator_id})",
                header.generator
            )));
        }
        let (kind, device) = g.kind_device();
        let mut take = |name: &str, want: [i64; 2]| -> Result<Tensor> {
            let v = t.remove(name).ok_or_else(|| bad(format!("no tensor '{name}'")))?;
            if v.size() != want {
                return Err(bad(format!("'{name}' has shape {:?}, expected {want:?}", v.size())));
            }
            Ok(v.to_kind(kind).to_device(device))
        };
        let colour = (g.cfg.colour_layers * g.cfg.hidden_dim) as i64;
        Ok(Self {
            w_s: take("w_s", [1, g.cfg.mapping_hidden_dim as i64])?,
            appearance: Film { gamma: take("gamma_a", [1, colour])?, beta: take("beta_a", [1, colour])? },
            pose: header.pose,
            z: None,
        })
    }

    /// Resolves a source against generator `g`.
    pub fn resolve(source: &Source, g: &Generator, generator_id: &str) -> Result<Self> {
        match source {
            Source::Seed(s) => Ok(Self::from_seed(g, *s)),
            Source::Features(p) => Self::load(p, g, generator_id),
            Source::Image(p) => Err(Error::Invalid(format!(
                "source {}: invert the photo first (gdrf-invert {} --pose PITCH,YAW --out DIR) and pass DIR/features.safetensors",
                p.display(),
                p.display()
            ))),
        }
    }
}

/// What an interpolation moves.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Interpolate {
    Shape,
    Appearance,
    Both,
}

/// The features a fraction `t` of the way from `a` to `b`, moving only what `what` says
/// (the rest stays `a`'s): codes are slerped when both sources have one (seeds), features
/// lerped otherwise.
pub fn interpolate(g: &Generator, a: &Features, b: &Features, t: f64, what: Interpolate) -> Features {
    tch::no_grad(|| {
        let by_code = match (&a.z, &b.z) {
            (Some(za), Some(zb)) => Some(slerp(za, zb, t)),
            _ => None,
        };
        let lerp = |x: &Tensor, y: &Tensor| x + (y - x) * t;
        let (shape, app) = (what != Interpolate::Appearance, what != Interpolate::Shape);
        let w_s = match (&by_code, shape) {
            (_, false) => a.w_s.shallow_clone(),
            (Some(z), true) => g.shape_w(z),
            (None, true) => lerp(&a.w_s, &b.w_s),
        };
        let appearance = match (&by_code, app) {
            (_, false) => Film { gamma: a.appearance.gamma.shallow_clone(), beta: a.appearance.beta.shallow_clone() },
            (Some(z), true) => g.appearance_from_z(z, None),
            (None, true) => Film {
                gamma: lerp(&a.appearance.gamma, &b.appearance.gamma),
                beta: lerp(&a.appearance.beta, &b.appearance.beta),
            },
        };
        Features { w_s, appearance, pose: a.pose, z: None }
    })
}

/// Spherical interpolation of codes `(1, Z)` (linear when they are parallel); the ends are
/// the codes themselves, exactly (the sine ratios there round off by an ulp).
pub fn slerp(a: &Tensor, b: &Tensor, t: f64) -> Tensor {
    if t == 0.0 {
        return a.copy();
    }
    if t == 1.0 {
        return b.copy();
    }
    let (na, nb) = (a.norm().double_value(&[]), b.norm().double_value(&[]));
    let cos = (a * b).sum(a.kind()).double_value(&[]) / (na * nb).max(1e-12);
    let omega = cos.clamp(-1.0, 1.0).acos();
    if omega.sin().abs() < 1e-6 {
        return a + (b - a) * t;
    }
    a * (((1.0 - t) * omega).sin() / omega.sin()) + b * ((t * omega).sin() / omega.sin())
}

/// Modulations for rendering: the shape of `shape` and the appearance of `appearance`,
/// both pulled toward the mean by `trunc` when given (ψ acts on the raw mapping outputs, to
/// which γ = 15·f + 30 and β are linear).
pub fn latents(g: &Generator, shape: &Features, appearance: &Features, trunc: Option<&Truncation>) -> Latents {
    tch::no_grad(|| {
        let shape_film = g.shape_from_w(&shape.w_s, trunc);
        let app = &appearance.appearance;
        let appearance_film = match trunc {
            Some(t) if t.psi != 1.0 => {
                let mean = Film::from_raw(&t.appearance_mean);
                Film {
                    gamma: &mean.gamma + (&app.gamma - &mean.gamma) * t.psi,
                    beta: &mean.beta + (&app.beta - &mean.beta) * t.psi,
                }
            }
            _ => Film { gamma: app.gamma.shallow_clone(), beta: app.beta.shallow_clone() },
        };
        Latents { shape: shape_film, appearance: appearance_film }
    })
}

/// A generator's identity: FNV-1a (64 bit) over its configuration and every parameter
/// (names, shapes and float32 values, in name order), as 16 hex digits. Feature files carry
/// it, so that features are never applied to a generator they were not made with.
pub fn generator_id(vs: &nn::VarStore, g: &Generator) -> String {
    const PRIME: u64 = 0x100_0000_01b3;
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut eat = |bytes: &[u8]| {
        for &b in bytes {
            h = (h ^ b as u64).wrapping_mul(PRIME);
        }
    };
    eat(identity_config(&g.cfg).as_bytes());
    let mut vars: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
    vars.sort_by(|a, b| a.0.cmp(&b.0));
    for (name, t) in vars {
        eat(name.as_bytes());
        for d in t.size() {
            eat(&d.to_le_bytes());
        }
        let t = t.detach().to_kind(Kind::Float).to_device(Device::Cpu).contiguous();
        let mut buf = vec![0u8; t.numel() * 4];
        if t.f_copy_data_u8(&mut buf, t.numel()).is_ok() {
            eat(&buf);
        }
    }
    format!("{h:016x}")
}

/// The config as [`generator_id`] hashes it: a SIREN generator's as written before the
/// `template` key existed, so that the feature and initialiser files made for it then (the
/// shipped model's initialiser among them) still match it.
fn identity_config(cfg: &GeneratorConfig) -> String {
    let json = serde_json::to_string(cfg).unwrap_or_default();
    match cfg.template {
        TemplateKind::Siren => json.replacen(r#","template":"siren""#, "", 1),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small() -> (nn::VarStore, Generator) {
        tch::manual_seed(1);
        let vs = nn::VarStore::new(Device::Cpu);
        let cfg = GeneratorConfig::tiny();
        let g = Generator::new(&vs.root(), &cfg).unwrap();
        (vs, g)
    }

    /// A SIREN generator's identity hashes its config without the `template` key, exactly
    /// as before the key existed (the tiny config's JSON as written then).
    #[test]
    fn siren_identities_are_those_made_before_the_template_key() {
        let old = r#"{"latent_dim":8,"hidden_dim":16,"mapping_hidden_dim":16,"trunk_layers":5,"color_layers":4,"deform_layers":4,"correct_scale":100.0,"deform_scale":1.0,"deform_head_frequency":0.0,"deform_head_bias":"uniform"}"#;
        assert_eq!(identity_config(&GeneratorConfig::tiny()), old);
        assert!(serde_json::to_string(&GeneratorConfig::tiny()).unwrap().contains(r#""template":"siren""#));
    }

    #[test]
    fn sources_parse_and_bad_ones_are_named() {
        assert_eq!("seed:42".parse::<Source>().unwrap(), Source::Seed(42));
        for (s, want) in
            [("seed:x", "not an integer"), ("foo.txt", "unknown kind"), ("missing.safetensors", "no such file")]
        {
            let e = s.parse::<Source>().unwrap_err().to_string();
            assert!(e.contains(s) && e.contains(want), "{s}: {e}");
        }
    }

    #[test]
    fn features_round_trip_and_refuse_another_generator() {
        let (vs, g) = small();
        let id = generator_id(&vs, &g);
        let dir = std::env::temp_dir().join(format!("gdrf-features-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("a.safetensors");
        let mut f = Features::from_seed(&g, 3);
        f.pose = Some((1.0, -0.5));
        f.save(&path, &id).unwrap();
        let back = Features::load(&path, &g, &id).unwrap();
        assert!(back.w_s.equal(&f.w_s) && back.appearance.gamma.equal(&f.appearance.gamma));
        assert!(back.appearance.beta.equal(&f.appearance.beta));
        assert_eq!(back.pose, Some((1.0, -0.5)));
        assert_eq!(format!("{:?}", "seed:3".parse::<Source>().unwrap()), "Seed(3)");
        // Another generator (other weights): its identity differs and the file is refused.
        let (vs2, g2) = {
            tch::manual_seed(2);
            let vs = nn::VarStore::new(Device::Cpu);
            let g = Generator::new(&vs.root(), &g.cfg).unwrap();
            (vs, g)
        };
        let id2 = generator_id(&vs2, &g2);
        assert_ne!(id, id2);
        let e = Features::load(&path, &g2, &id2).unwrap_err().to_string();
        assert!(e.contains("a.safetensors") && e.contains(&id) && e.contains(&id2), "{e}");
        // A wrongly shaped tensor is named.
        let wrong = Features { w_s: Tensor::zeros([1, 5], (Kind::Float, Device::Cpu)), ..Features::from_seed(&g, 3) };
        assert!(back.z.is_none());
        wrong.save(&path, &id).unwrap();
        let e = Features::load(&path, &g, &id).unwrap_err().to_string();
        assert!(e.contains("'w_s'") && e.contains("[1, 16]"), "{e}");
        // An unreadable file (not safetensors) is named.
        std::fs::write(&path, b"not a feature file").unwrap();
        let e = Features::load(&path, &g, &id).unwrap_err().to_string();
        assert!(e.contains("a.safetensors"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_seed_gives_the_latents_of_its_code() {
        let (_vs, g) = small();
        let f = Features::from_seed(&g, 7);
        let z = seeded_randn(&[1, 8], 7);
        let want = tch::no_grad(|| g.latents(&z, &z, None)).unwrap();
        let got = latents(&g, &f, &f, None);
        assert!(got.shape.gamma.allclose(&want.shape.gamma, 1e-6, 1e-6, false));
        assert!(got.appearance.beta.allclose(&want.appearance.beta, 1e-6, 1e-6, false));
        // Truncated: the same as truncating the codes' raw outputs.
        let t = g.truncation(0.5, 100, 0);
        let want = tch::no_grad(|| g.latents(&z, &z, Some(&t))).unwrap();
        let got = latents(&g, &f, &f, Some(&t));
        assert!(got.shape.gamma.allclose(&want.shape.gamma, 1e-5, 1e-5, false));
        assert!(got.appearance.gamma.allclose(&want.appearance.gamma, 1e-5, 1e-5, false));
        // Interpolation: the ends are the sources; moving only the appearance keeps the shape.
        let b = Features::from_seed(&g, 8);
        let start = interpolate(&g, &f, &b, 0.0, Interpolate::Both);
        let end = interpolate(&g, &f, &b, 1.0, Interpolate::Both);
        assert!(start.w_s.equal(&f.w_s) && end.w_s.equal(&b.w_s), "the ends are the sources, exactly");
        assert!(start.appearance.gamma.equal(&f.appearance.gamma) && end.appearance.beta.equal(&b.appearance.beta));
        let half = interpolate(&g, &f, &b, 0.5, Interpolate::Appearance);
        assert!(half.w_s.equal(&f.w_s) && !half.appearance.gamma.allclose(&f.appearance.gamma, 1e-6, 1e-6, false));
        let s = slerp(&Tensor::from_slice(&[1.0f32, 0.0]), &Tensor::from_slice(&[0.0f32, 1.0]), 0.5);
        assert!(s.allclose(&Tensor::from_slice(&[0.5f32.sqrt(), 0.5f32.sqrt()]), 1e-6, 1e-6, false));
        let e = Features::resolve(&Source::Image("x.png".into()), &g, "id").unwrap_err().to_string();
        assert!(e.contains("x.png") && e.contains("gdrf-invert"), "{e}");
    }
}
