//! Checkpoints: safetensors files with named tensors and a JSON header (metadata key
//! `gdrf`) that describes the model. Writes are atomic; loading is strict and every
//! mismatch names the tensor and both shapes.
use crate::config::{CameraConfig, GeneratorConfig};
use crate::field::generator::Generator;
use crate::paths::{io_err, write_atomic};
use crate::{Error, Result};
use safetensors::tensor::{Dtype, TensorView};
use safetensors::SafeTensors;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use tch::{nn, Device, Kind, Tensor};

/// Metadata key holding the JSON header.
pub const HEADER_KEY: &str = "gdrf";
/// 2: adds the training state (`model = "training_state"`, the `training` header) and
/// refuses non-finite tensors. Version 1 files (generators) still load.
pub const FORMAT_VERSION: u32 = 2;

/// The JSON header of a generator checkpoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Header {
    pub format_version: u32,
    /// What the tensors are: `"generator"`, or `"training_state"` (generator, EMA and
    /// discriminator parameters and both optimisers' moments, under the prefixes
    /// `generator.`, `ema.`, `discriminator.`, `adam_g.`, `adam_d.`).
    pub model: String,
    pub generator: GeneratorConfig,
    /// The camera the model was trained with, when known.
    #[serde(default)]
    pub camera: Option<CameraConfig>,
    /// Free-form provenance (training step, converter, …).
    #[serde(default)]
    pub info: BTreeMap<String, String>,
    /// Training state: step, stage, counters and the whole resolved training config
    /// (training checkpoints only; its schema belongs to [`crate::train`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub training: Option<serde_json::Value>,
    /// CRC-32 of the tensors ([`checksum`]), written by [`to_bytes`] and checked by
    /// [`load`], which then clears it: a loaded header equals the one that was saved. Files
    /// written before it existed have none and load unchecked.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub checksum: Option<String>,
}

/// The generator header's `info` key holding the resolution of its last training step.
pub const RESOLUTION_INFO: &str = "resolution";
/// The generator header's `info` key holding the samples per ray (coarse + fine) of its last
/// training step.
pub const SAMPLES_PER_RAY_INFO: &str = "samples_per_ray";

impl Header {
    /// The resolution of the generator's last training step, when its run recorded it.
    pub fn trained_resolution(&self) -> Option<i64> {
        self.info.get(RESOLUTION_INFO)?.parse().ok()
    }

    /// The coarse samples per ray of its last training step (half of coarse + fine), when
    /// recorded: what `--samples`/`--steps` mean in the tools.
    pub fn trained_coarse_samples(&self) -> Option<i64> {
        let n: i64 = self.info.get(SAMPLES_PER_RAY_INFO)?.parse().ok()?;
        Some((n / 2).max(2))
    }

    pub fn generator(generator: GeneratorConfig, camera: Option<CameraConfig>) -> Self {
        Self {
            format_version: FORMAT_VERSION,
            model: "generator".into(),
            generator,
            camera,
            info: BTreeMap::new(),
            training: None,
            checksum: None,
        }
    }
}

fn dtype_of(kind: Kind) -> Result<Dtype> {
    match kind {
        Kind::Float => Ok(Dtype::F32),
        Kind::Double => Ok(Dtype::F64),
        Kind::Half => Ok(Dtype::F16),
        Kind::BFloat16 => Ok(Dtype::BF16),
        Kind::Int64 => Ok(Dtype::I64),
        k => Err(Error::Invalid(format!("cannot store tensors of kind {k:?}"))),
    }
}

/// Whether every element of a floating-point tensor is finite (other kinds always are).
pub fn is_finite(t: &Tensor) -> bool {
    match t.kind() {
        Kind::Float | Kind::Double | Kind::Half | Kind::BFloat16 => bool::try_from(t.isfinite().all()).unwrap_or(false),
        _ => true,
    }
}

/// Serialises named tensors and the header, with their [`checksum`], to safetensors bytes.
/// A tensor with a NaN or an infinity is an error naming it: such a checkpoint is never
/// written.
pub fn to_bytes(tensors: &[(String, Tensor)], header: &Header) -> Result<Vec<u8>> {
    let sorted: BTreeMap<&str, &Tensor> = tensors.iter().map(|(n, t)| (n.as_str(), t)).collect();
    let header = Header { checksum: Some(checksum(sorted)?), ..header.clone() };
    let json = serde_json::to_string(&header)?;
    tensors_to_bytes(tensors, HEADER_KEY, &json)
}

/// CRC-32 (hex) of tensors in name order: each one's name, dtype, shape and bytes as
/// stored. A flipped bit in a file's tensor data still parses; this tells.
pub fn checksum<'a>(tensors: impl IntoIterator<Item = (&'a str, &'a Tensor)>) -> Result<String> {
    let mut h = crc32fast::Hasher::new();
    for (name, t) in tensors {
        let t = t.detach().to_device(Device::Cpu).contiguous();
        let mut buf = vec![0u8; t.numel() * t.kind().elt_size_in_bytes()];
        t.f_copy_data_u8(&mut buf, t.numel())?;
        h.update(name.as_bytes());
        h.update(format!("{:?}{:?}", dtype_of(t.kind())?, t.size()).as_bytes());
        h.update(&buf);
    }
    Ok(format!("{:08x}", h.finalize()))
}

/// Serialises named tensors with one JSON metadata entry under `key` (other models'
/// files: the evaluation's probe). Non-finite tensors are refused as in [`to_bytes`].
pub fn tensors_to_bytes(tensors: &[(String, Tensor)], key: &str, json: &str) -> Result<Vec<u8>> {
    let mut data = Vec::with_capacity(tensors.len());
    for (name, t) in tensors {
        if !is_finite(t) {
            return Err(Error::Invalid(format!(
                "tensor '{name}' holds NaN or infinite values; refusing to write a checkpoint"
            )));
        }
        let t = t.detach().to_device(Device::Cpu).contiguous();
        let mut buf = vec![0u8; t.numel() * t.kind().elt_size_in_bytes()];
        t.f_copy_data_u8(&mut buf, t.numel())?;
        let shape: Vec<usize> = t.size().iter().map(|&d| d as usize).collect();
        data.push((name.clone(), dtype_of(t.kind())?, shape, buf));
    }
    let views = data
        .iter()
        .map(|(n, d, s, b)| TensorView::new(*d, s.clone(), b).map(|v| (n.clone(), v)))
        .collect::<std::result::Result<Vec<_>, _>>()
        .map_err(|e| Error::Invalid(format!("tensor layout: {e}")))?;
    let meta = HashMap::from([(key.to_string(), json.to_string())]);
    safetensors::serialize(views, Some(meta)).map_err(|e| Error::Invalid(format!("serialise: {e}")))
}

/// Saves named tensors with a header, atomically.
pub fn save(path: &Path, tensors: &[(String, Tensor)], header: &Header) -> Result<()> {
    write_atomic(path, &to_bytes(tensors, header)?)
}

/// A checkpoint read from disk: header and CPU tensors by name.
#[derive(Debug)]
pub struct Checkpoint {
    pub path: PathBuf,
    pub header: Header,
    pub tensors: BTreeMap<String, Tensor>,
}

/// Reads and validates a checkpoint file (layout, header); tensors land on the CPU.
pub fn load(path: &Path) -> Result<Checkpoint> {
    let (json, tensors) = load_tensors_with(path, HEADER_KEY)?;
    let not = |reason: String| Error::NotACheckpoint { path: path.to_path_buf(), reason };
    let mut header: Header = serde_json::from_str(&json).map_err(|e| not(format!("bad header: {e}")))?;
    if header.format_version > FORMAT_VERSION {
        return Err(not(format!(
            "format version {} is newer than this program's {FORMAT_VERSION}",
            header.format_version
        )));
    }
    if let Some(stored) = header.checksum.take() {
        let found = checksum(tensors.iter().map(|(n, t)| (n.as_str(), t)))?;
        if found != stored {
            return Err(not(format!(
                "its tensors do not match the checksum written with them (stored {stored}, found {found}): \
                 the file was damaged after it was written"
            )));
        }
    }
    Ok(Checkpoint { path: path.to_path_buf(), header, tensors })
}

/// Reads a safetensors file with a JSON metadata entry under `key`: the JSON and the
/// CPU tensors by name (non-finite tensors refused).
pub fn load_tensors_with(path: &Path, key: &str) -> Result<(String, BTreeMap<String, Tensor>)> {
    let bytes = std::fs::read(path).map_err(io_err(path))?;
    let not = |reason: String| Error::NotACheckpoint { path: path.to_path_buf(), reason };
    let st = SafeTensors::deserialize(&bytes).map_err(|e| {
        not(match e {
            safetensors::SafeTensorError::MetadataIncompleteBuffer | safetensors::SafeTensorError::InvalidOffset(_) => {
                format!("the file is truncated or corrupt ({e}); it holds {} bytes", bytes.len())
            }
            _ => format!("not a safetensors file ({e})"),
        })
    })?;
    let (_, meta) = SafeTensors::read_metadata(&bytes).map_err(|e| not(e.to_string()))?;
    let json = meta
        .metadata()
        .as_ref()
        .and_then(|m| m.get(key))
        .ok_or_else(|| not(format!("a safetensors file without the '{key}' header")))?
        .clone();
    let mut tensors = BTreeMap::new();
    for (name, view) in st.tensors() {
        let kind = match view.dtype() {
            Dtype::F32 => Kind::Float,
            Dtype::F64 => Kind::Double,
            Dtype::F16 => Kind::Half,
            Dtype::BF16 => Kind::BFloat16,
            Dtype::I64 => Kind::Int64,
            d => return Err(Error::DType { path: path.to_path_buf(), name, found: format!("{d:?}") }),
        };
        let shape: Vec<i64> = view.shape().iter().map(|&d| d as i64).collect();
        let t = Tensor::from_data_size(view.data(), &shape, kind);
        if !is_finite(&t) {
            return Err(not(format!("tensor '{name}' holds NaN or infinite values")));
        }
        tensors.insert(name, t);
    }
    Ok((json, tensors))
}

impl Checkpoint {
    /// Copies the tensors into `vs`. Every variable must be present with its exact shape,
    /// and the file may hold nothing else.
    pub fn load_into(&self, vs: &mut nn::VarStore) -> Result<()> {
        copy_into(&self.path, &self.tensors, vs)
    }
}

/// Copies tensors read from `path` into `vs`: every variable must be present with its
/// exact shape, and nothing else may be there (errors name the tensor and both shapes).
pub fn copy_into(path: &Path, tensors: &BTreeMap<String, Tensor>, vs: &mut nn::VarStore) -> Result<()> {
    let path = &path.to_path_buf();
    let shape = |t: &Tensor| t.size().iter().map(|&d| d as usize).collect::<Vec<_>>();
    let vars = vs.variables();
    for (name, t) in tensors {
        if !vars.contains_key(name) {
            return Err(Error::UnexpectedTensor { path: path.clone(), name: name.clone(), found: shape(t) });
        }
    }
    let mut names: Vec<_> = vars.keys().cloned().collect();
    names.sort();
    tch::no_grad(|| {
        for name in names {
            let mut var = vars[&name].shallow_clone();
            let src = tensors.get(&name).ok_or_else(|| Error::MissingTensor {
                path: path.clone(),
                name: name.clone(),
                expected: shape(&var),
            })?;
            if src.size() != var.size() {
                return Err(Error::ShapeMismatch {
                    path: path.clone(),
                    name: name.clone(),
                    found: shape(src),
                    expected: shape(&var),
                });
            }
            var.copy_(&src.to_kind(var.kind()).to_device(var.device()));
        }
        Ok(())
    })
}

/// A generator with its parameters.
pub struct LoadedGenerator {
    pub vs: nn::VarStore,
    pub generator: Generator,
    pub header: Header,
}

/// Saves a generator's parameters and configuration.
pub fn save_generator(path: &Path, vs: &nn::VarStore, header: &Header) -> Result<()> {
    let mut tensors: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
    tensors.sort_by(|a, b| a.0.cmp(&b.0));
    save(path, &tensors, header)
}

/// Refuses a file whose header describes an invalid generator, or one far larger than the
/// `tensors` it stores (a damaged or hostile header), before the generator is built:
/// building it would allocate what the header claims. Within twice the stored values
/// (plus 64 Ki), loading goes on and names the tensors that differ.
pub fn check_generator_size<'a>(
    path: &Path,
    cfg: &GeneratorConfig,
    tensors: impl IntoIterator<Item = &'a Tensor>,
) -> Result<()> {
    let not = |reason: String| Error::NotACheckpoint { path: path.to_path_buf(), reason };
    cfg.validate().map_err(|e| not(format!("its header's generator: {e}")))?;
    let stored: u128 = tensors.into_iter().map(|t| t.numel() as u128).sum();
    let promised = cfg.parameter_count();
    if promised > stored.saturating_mul(2).saturating_add(1 << 16) {
        return Err(not(format!(
            "its header describes a generator of {promised} parameters, far more than the {stored} values it stores"
        )));
    }
    Ok(())
}

/// Reads a generator checkpoint, or a training checkpoint as its EMA generator: the `ema.`
/// tensors under their generator names and the header a generator exported at that step
/// carries (model `"generator"`, no training state), size-checked.
fn load_as_generator(path: &Path) -> Result<Checkpoint> {
    let mut ckpt = load(path)?;
    match ckpt.header.model.as_str() {
        "generator" => {}
        "training_state" => {
            ckpt.tensors = std::mem::take(&mut ckpt.tensors)
                .into_iter()
                .filter_map(|(n, t)| n.strip_prefix("ema.").map(|n| (n.to_string(), t)))
                .collect();
            ckpt.header.model = "generator".into();
            ckpt.header.training = None;
        }
        other => {
            return Err(Error::NotACheckpoint {
                path: path.to_path_buf(),
                reason: format!("it holds a '{other}', not a generator"),
            })
        }
    }
    check_generator_size(path, &ckpt.header.generator, ckpt.tensors.values())?;
    Ok(ckpt)
}

/// Writes to `out` (atomically) the generator of checkpoint `path`: a training
/// checkpoint's EMA generator, the file its run exported at that step (`gdrf-train ship`
/// uses it where a run's evaluation folder lost its copy).
pub fn export_generator(path: &Path, out: &Path) -> Result<Header> {
    let ckpt = load_as_generator(path)?;
    let tensors: Vec<(String, Tensor)> = ckpt.tensors.into_iter().collect();
    save(out, &tensors, &ckpt.header)?;
    Ok(ckpt.header)
}

/// Loads a generator checkpoint onto `device` in `kind` (Float or Double). A training
/// checkpoint gives its EMA generator (what samples and evaluation use).
pub fn load_generator(path: &Path, device: Device, kind: Kind) -> Result<LoadedGenerator> {
    let ckpt = load_as_generator(path)?;
    let mut vs = nn::VarStore::new(device);
    let generator = Generator::new(&vs.root(), &ckpt.header.generator)?;
    if kind == Kind::Double {
        vs.double();
    }
    ckpt.load_into(&mut vs)?;
    Ok(LoadedGenerator { vs, generator, header: ckpt.header })
}

/// Writes to `out` the generator whose every parameter is `(1 − t)·a + t·b`, for two
/// generators of one architecture (a training checkpoint gives its EMA generator).
///
/// When `b` was trained on from `a`, the straight line between them can keep what each
/// does better (weight-space ensembling, "WiSE-FT"; Wortsman et al., CVPR 2022): the
/// default chairs model before the campaign was such a blend (docs/campaign-log.md, "What kept codes apart on the CPU (measured)"). Both must
/// share the generator config and, where both record one, the camera; `t` lies in [0, 1].
///
/// `groups` gives the parameters under a name prefix their own weight (`template.trunk`
/// covers `template.trunk.0.weight` …; the longest matching prefix wins): the sub-networks
/// of two such ends need not sit best at one point of the line (layer-wise merging). A
/// prefix that names no parameter is an error listing the ones there are. The header
/// records both sources, their provenance, `t` and the groups.
pub fn save_interpolated(a: &Path, b: &Path, t: f64, groups: &[(String, f64)], out: &Path) -> Result<Header> {
    if !(0.0..=1.0).contains(&t) {
        return Err(Error::Invalid(format!("t is {t}, expected a weight in [0, 1] (0 gives the first generator)")));
    }
    for (i, (prefix, tg)) in groups.iter().enumerate() {
        if !(0.0..=1.0).contains(tg) {
            return Err(Error::Invalid(format!("the weight of {prefix} is {tg}, expected a weight in [0, 1]")));
        }
        // Two weights for one prefix would leave the choice to the order they came in.
        if groups[..i].iter().any(|(p, _)| p == prefix) {
            return Err(Error::Invalid(format!("{prefix} is given a weight twice, expected each prefix once")));
        }
    }
    let ga = load_generator(a, Device::Cpu, Kind::Float)?;
    let gb = load_generator(b, Device::Cpu, Kind::Float)?;
    if ga.header.generator != gb.header.generator {
        let (ja, jb) = (serde_json::to_value(&ga.header.generator), serde_json::to_value(&gb.header.generator));
        let differ = match (ja, jb) {
            (Ok(serde_json::Value::Object(ma)), Ok(serde_json::Value::Object(mb))) => ma
                .iter()
                .filter(|(k, v)| mb.get(*k) != Some(*v))
                .map(|(k, v)| format!("{k} {v} and {}", mb.get(k).unwrap_or(&serde_json::Value::Null)))
                .collect::<Vec<_>>()
                .join(", "),
            _ => format!("{:?} and {:?}", ga.header.generator, gb.header.generator),
        };
        return Err(Error::Invalid(format!(
            "{} and {} have different generator configs ({differ}); only generators of one config interpolate",
            a.display(),
            b.display()
        )));
    }
    let camera = match (&ga.header.camera, &gb.header.camera) {
        (Some(ca), Some(cb)) if ca != cb => {
            return Err(Error::Invalid(format!(
                "{} and {} were trained with different cameras ({ca:?} and {cb:?})",
                a.display(),
                b.display()
            )))
        }
        (ca, cb) => ca.clone().or_else(|| cb.clone()),
    };
    let vb = gb.vs.variables();
    let va = ga.vs.variables();
    let under = |name: &str, prefix: &str| {
        name.strip_prefix(prefix).is_some_and(|rest| rest.is_empty() || rest.starts_with('.'))
    };
    for (prefix, _) in groups {
        if !va.keys().any(|name| under(name, prefix)) {
            // Parameter names less their last part, and less a layer index before it.
            let module = |n: &str| {
                let base = n.rsplit_once('.').map_or(n, |(m, _)| m);
                match base.rsplit_once('.') {
                    Some((m, i)) if i.parse::<usize>().is_ok() => m.to_string(),
                    _ => base.to_string(),
                }
            };
            let mut modules: Vec<String> = va.keys().map(|n| module(n)).collect();
            modules.sort();
            modules.dedup();
            return Err(Error::Invalid(format!(
                "{prefix} names no parameter of the generator; expected a prefix of a parameter name such as {}",
                modules.join(", ")
            )));
        }
    }
    let weight = |name: &str| {
        groups.iter().filter(|(p, _)| under(name, p)).max_by_key(|(p, _)| p.len()).map_or(t, |(_, tg)| *tg)
    };
    let mut tensors: Vec<(String, Tensor)> = tch::no_grad(|| {
        va.into_iter().map(|(name, ta)| {
            // Same config, so the same names and shapes.
            let w = weight(&name);
            let mixed = &ta * (1.0 - w) + &vb[&name] * w;
            (name, mixed)
        })
    })
    .collect();
    tensors.sort_by(|x, y| x.0.cmp(&y.0));
    let mut header = Header::generator(ga.header.generator.clone(), camera);
    let mut rule = format!("(1 - t)·from + t·to, t = {t}");
    for (prefix, tg) in groups {
        rule.push_str(&format!("; t = {tg} under {prefix}"));
    }
    header.info.insert("interpolated".into(), rule);
    header.info.insert("from".into(), a.display().to_string());
    header.info.insert("to".into(), b.display().to_string());
    for (prefix, h) in [("from", &ga.header), ("to", &gb.header)] {
        for (k, v) in &h.info {
            header.info.insert(format!("{prefix}.{k}"), v.clone());
        }
    }
    // What both sources last trained at, where they agree, for the evaluation to read.
    for key in [RESOLUTION_INFO, SAMPLES_PER_RAY_INFO] {
        if let (Some(x), Some(y)) = (ga.header.info.get(key), gb.header.info.get(key)) {
            if x == y {
                header.info.insert(key.into(), x.clone());
            }
        }
    }
    save(out, &tensors, &header)?;
    Ok(header)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn interpolation_mixes_every_parameter_and_refuses_mismatches() {
        let dir = std::env::temp_dir().join(format!("gdrf-ckpt-mix-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let cfg = GeneratorConfig { mapping_hidden_dim: 8, latent_dim: 4, ..GeneratorConfig::tiny() };
        let write = |name: &str, cfg: &GeneratorConfig, camera: Option<CameraConfig>, fill: f64| {
            let vs = nn::VarStore::new(Device::Cpu);
            let _g = Generator::new(&vs.root(), cfg).unwrap();
            tch::no_grad(|| {
                for (_, mut v) in vs.variables() {
                    let _ = v.fill_(fill);
                }
            });
            let path = dir.join(name);
            let mut header = Header::generator(cfg.clone(), camera);
            header.info.insert("step".into(), format!("{fill}"));
            header.info.insert("resolution".into(), "32".into());
            header.info.insert("samples_per_ray".into(), format!("{}", 8.0 * fill));
            save_generator(&path, &vs, &header).unwrap();
            path
        };
        let a = write("a.safetensors", &cfg, Some(CameraConfig::chair()), 1.0);
        let b = write("b.safetensors", &cfg, None, 3.0);
        let out = dir.join("mix.safetensors");
        let header = save_interpolated(&a, &b, 0.25, &[], &out).unwrap();
        assert_eq!(header.camera, Some(CameraConfig::chair()));
        assert_eq!(header.info["from.step"], "1");
        assert_eq!(header.info["to.step"], "3");
        // The training resolution both share is kept; the samples per ray they differ in are not.
        assert_eq!(header.info["resolution"], "32");
        assert!(!header.info.contains_key("samples_per_ray"), "{:?}", header.info);
        let mixed = load_generator(&out, Device::Cpu, Kind::Float).unwrap();
        assert_eq!(mixed.header, header);
        let vars = mixed.vs.variables();
        assert!(!vars.is_empty());
        for (name, v) in vars {
            // 0.75 · 1 + 0.25 · 3 = 1.5, exactly in float32.
            assert!(v.eq(1.5).all().int64_value(&[]) == 1, "{name}");
        }
        // The ends give the sources back exactly.
        for (t, source) in [(0.0, &a), (1.0, &b)] {
            save_interpolated(&a, &b, t, &[], &out).unwrap();
            let got = load_generator(&out, Device::Cpu, Kind::Float).unwrap().vs.variables();
            let want = load_generator(source, Device::Cpu, Kind::Float).unwrap().vs.variables();
            for (name, v) in got {
                assert!(v.equal(&want[&name]), "t = {t}: {name}");
            }
        }
        // Groups: the longest matching prefix wins, at a name-part boundary, and the rest
        // keep t. 1 and 3 mixed at 0.5 give 2, at 0.75 give 2.5, at 0.25 give 1.5.
        let groups = [("template".to_string(), 0.5), ("template.trunk".to_string(), 0.75)];
        let header = save_interpolated(&a, &b, 0.25, &groups, &out).unwrap();
        assert_eq!(
            header.info["interpolated"],
            "(1 - t)·from + t·to, t = 0.25; t = 0.5 under template; t = 0.75 under template.trunk"
        );
        let vars = load_generator(&out, Device::Cpu, Kind::Float).unwrap().vs.variables();
        let mut seen = [0; 3];
        for (name, v) in vars {
            let (want, k) = if name.starts_with("template.trunk.") {
                (2.5, 0)
            } else if name.starts_with("template.") {
                (2.0, 1)
            } else {
                (1.5, 2)
            };
            seen[k] += 1;
            assert!(v.eq(want).all().int64_value(&[]) == 1, "{name} should be {want}");
        }
        assert!(seen.iter().all(|&n| n > 0), "every group has parameters: {seen:?}");
        // `template.tr` is not a name part: it names nothing, and the error lists what does.
        let e = save_interpolated(&a, &b, 0.25, &[("template.tr".into(), 0.5)], &out).unwrap_err().to_string();
        assert!(
            e.contains("template.tr names no parameter") && e.contains("template.sigma_head, template.trunk"),
            "{e}"
        );
        let twice = [("deform".to_string(), 0.5), ("deform".to_string(), 0.5)];
        let e = save_interpolated(&a, &b, 0.25, &twice, &out).unwrap_err().to_string();
        assert!(e.contains("deform is given a weight twice"), "{e}");
        let e = save_interpolated(&a, &b, 0.25, &[("deform".into(), 2.0)], &out).unwrap_err().to_string();
        assert!(e.contains("the weight of deform is 2") && e.contains("[0, 1]"), "{e}");
        let e = save_interpolated(&a, &b, 1.5, &[], &out).unwrap_err().to_string();
        assert!(e.contains("t is 1.5") && e.contains("[0, 1]"), "{e}");
        let e = save_interpolated(&a, &b, f64::NAN, &[], &out).unwrap_err().to_string();
        assert!(e.contains("t is NaN"), "{e}");
        let wide = write("wide.safetensors", &GeneratorConfig { hidden_dim: 8, ..cfg.clone() }, None, 2.0);
        let e = save_interpolated(&a, &wide, 0.5, &[], &out).unwrap_err().to_string();
        assert!(e.contains("different generator configs (hidden_dim 16 and 8)"), "{e}");
        let car = write("car.safetensors", &cfg, Some(CameraConfig::car()), 2.0);
        let e = save_interpolated(&a, &car, 0.5, &[], &out).unwrap_err().to_string();
        assert!(e.contains("different cameras"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn round_trip_is_exact() {
        let dir = std::env::temp_dir().join(format!("gdrf-ckpt-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("g.safetensors");
        let cfg = GeneratorConfig { mapping_hidden_dim: 8, latent_dim: 4, ..GeneratorConfig::tiny() };
        let vs = nn::VarStore::new(Device::Cpu);
        let _g = Generator::new(&vs.root(), &cfg).unwrap();
        save_generator(&path, &vs, &Header::generator(cfg.clone(), Some(CameraConfig::car()))).unwrap();
        let back = load_generator(&path, Device::Cpu, Kind::Float).unwrap();
        assert_eq!(back.header.generator, cfg);
        assert_eq!(back.header.camera, Some(CameraConfig::car()));
        let a = vs.variables();
        for (name, t) in back.vs.variables() {
            assert!(t.equal(&a[&name]), "{name}");
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// The header written today names the template; a file written before the key existed
    /// loads as SIREN with the same parameters; a template no program knows is an error
    /// naming the key.
    #[test]
    fn the_header_records_the_template_and_older_files_load_as_siren() {
        use crate::config::TemplateKind;
        let dir = std::env::temp_dir().join(format!("gdrf-ckpt-template-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("g.safetensors");
        let vs = nn::VarStore::new(Device::Cpu);
        let _g = Generator::new(&vs.root(), &GeneratorConfig::tiny()).unwrap();
        save_generator(&path, &vs, &Header::generator(GeneratorConfig::tiny(), None)).unwrap();
        let (json, tensors) = load_tensors_with(&path, HEADER_KEY).unwrap();
        let header: serde_json::Value = serde_json::from_str(&json).unwrap();
        assert_eq!(header["generator"]["template"], "siren", "{json}");
        // The same file as written before the key existed, and with a template no one knows.
        let rewrite = |template: Option<serde_json::Value>| {
            let mut h = header.clone();
            let g = h["generator"].as_object_mut().unwrap();
            match template {
                Some(t) => g.insert("template".into(), t),
                None => g.remove("template"),
            };
            let named: Vec<(String, Tensor)> = tensors.iter().map(|(n, t)| (n.clone(), t.shallow_clone())).collect();
            write_atomic(&path, &tensors_to_bytes(&named, HEADER_KEY, &h.to_string()).unwrap()).unwrap();
        };
        rewrite(None);
        let old = load_generator(&path, Device::Cpu, Kind::Float).unwrap();
        assert_eq!(old.header.generator.template, TemplateKind::Siren);
        assert_eq!(old.header.generator, GeneratorConfig::tiny());
        let a = vs.variables();
        for (name, t) in old.vs.variables() {
            assert!(t.equal(&a[&name]), "{name}");
        }
        for (value, shown) in [(serde_json::json!("triplane"), "triplane"), (serde_json::json!(3), "3")] {
            rewrite(Some(value));
            let e = load_generator(&path, Device::Cpu, Kind::Float).err().expect("refused").to_string();
            assert!(e.contains("generator.template") && e.contains(shown), "{e}");
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn non_finite_tensors_are_never_written_nor_loaded() {
        let dir = std::env::temp_dir().join(format!("gdrf-ckpt-nan-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("bad.safetensors");
        let header = Header::generator(GeneratorConfig::default(), None);
        let bad = Tensor::from_slice(&[1.0f32, f32::NAN]);
        let e = save(&path, &[("w".into(), bad)], &header).unwrap_err().to_string();
        assert!(e.contains("'w'") && e.contains("NaN"), "{e}");
        assert!(!path.exists());
        // A file holding an infinity (written by another tool) is refused on load.
        let inf = f32::INFINITY.to_le_bytes();
        let views = [("v".to_string(), TensorView::new(Dtype::F32, vec![1], &inf).unwrap())];
        let json = serde_json::to_string(&header).unwrap();
        let bytes = safetensors::serialize(views, Some(HashMap::from([(HEADER_KEY.to_string(), json)]))).unwrap();
        write_atomic(&path, &bytes).unwrap();
        let e = load(&path).unwrap_err().to_string();
        assert!(e.contains("'v'") && e.contains("infinite"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
