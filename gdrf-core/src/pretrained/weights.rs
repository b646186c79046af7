//! Frozen pretrained weights read from a safetensors file: every tensor is asked for by
//! name and shape, so a file with a missing or mis-shaped tensor is an error that names the
//! tensor and both shapes, and a file with tensors the network never asked for is reported
//! (a sign of the wrong file or an architecture mismatch).
use crate::{Error, Result};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use tch::{Device, Kind, Tensor};

pub struct Weights {
    path: PathBuf,
    tensors: BTreeMap<String, Tensor>,
    used: BTreeSet<String>,
    device: Device,
}

impl Weights {
    /// Reads every tensor of `path` (float32 on `device`).
    pub fn open(path: &Path, device: Device) -> Result<Self> {
        if !path.is_file() {
            return Err(Error::Io {
                path: path.to_path_buf(),
                err: std::io::Error::new(std::io::ErrorKind::NotFound, "weights file not found"),
            });
        }
        let list = Tensor::read_safetensors(path).map_err(|e| Error::NotACheckpoint {
            path: path.to_path_buf(),
            reason: format!("not a readable safetensors file: {e}"),
        })?;
        Ok(Self::from_tensors(path, list, device))
    }

    /// Wraps tensors already in memory (tests, random weights); `path` names them in errors.
    pub fn from_tensors(path: &Path, list: Vec<(String, Tensor)>, device: Device) -> Self {
        let tensors = list.into_iter().collect();
        Self { path: path.to_path_buf(), tensors, used: BTreeSet::new(), device }
    }

    /// The tensor `name`, which must have shape `shape`; float32 on the device, no gradient.
    pub fn get(&mut self, name: &str, shape: &[i64]) -> Result<Tensor> {
        let expected: Vec<usize> = shape.iter().map(|&d| d as usize).collect();
        let t = self.tensors.get(name).ok_or_else(|| Error::MissingTensor {
            path: self.path.clone(),
            name: name.to_string(),
            expected: expected.clone(),
        })?;
        if t.size() != shape {
            return Err(Error::ShapeMismatch {
                path: self.path.clone(),
                name: name.to_string(),
                found: t.size().iter().map(|&d| d as usize).collect(),
                expected,
            });
        }
        match t.kind() {
            Kind::Float | Kind::Double | Kind::Half | Kind::BFloat16 => {}
            k => return Err(Error::DType { path: self.path.clone(), name: name.to_string(), found: format!("{k:?}") }),
        }
        self.used.insert(name.to_string());
        Ok(t.to_kind(Kind::Float).to_device(self.device).detach())
    }

    /// Errors if the file holds float tensors that were never asked for; integer
    /// bookkeeping entries (BatchNorm's `num_batches_tracked`) are ignored.
    pub fn finish(self) -> Result<()> {
        for (name, t) in &self.tensors {
            let is_float = matches!(t.kind(), Kind::Float | Kind::Double | Kind::Half | Kind::BFloat16);
            if is_float && !self.used.contains(name) {
                return Err(Error::UnexpectedTensor {
                    path: self.path.clone(),
                    name: name.clone(),
                    found: t.size().iter().map(|&d| d as usize).collect(),
                });
            }
        }
        Ok(())
    }
}

/// An eval-mode convolution with an optional bias.
#[derive(Debug)]
pub struct Conv2d {
    pub weight: Tensor,
    pub bias: Option<Tensor>,
    pub stride: i64,
    pub padding: [i64; 2],
    pub groups: i64,
}

impl Conv2d {
    /// Reads `{prefix}.weight` of shape `(cout, cin / groups, kh, kw)` (and `{prefix}.bias`).
    #[allow(clippy::too_many_arguments)]
    pub fn load(
        w: &mut Weights,
        prefix: &str,
        cin: i64,
        cout: i64,
        k: [i64; 2],
        stride: i64,
        padding: [i64; 2],
        groups: i64,
        bias: bool,
    ) -> Result<Self> {
        let weight = w.get(&format!("{prefix}.weight"), &[cout, cin / groups, k[0], k[1]])?;
        let bias = if bias { Some(w.get(&format!("{prefix}.bias"), &[cout])?) } else { None };
        Ok(Self { weight, bias, stride, padding, groups })
    }

    pub fn forward(&self, x: &Tensor) -> Tensor {
        x.conv2d(&self.weight, self.bias.as_ref(), [self.stride, self.stride], self.padding, [1, 1], self.groups)
    }
}

/// Eval-mode BatchNorm2d (running statistics).
#[derive(Debug)]
pub struct BatchNorm {
    pub weight: Tensor,
    pub bias: Tensor,
    pub mean: Tensor,
    pub var: Tensor,
    pub eps: f64,
}

impl BatchNorm {
    /// Reads `{prefix}.{weight,bias,running_mean,running_var}` of `(c,)`.
    pub fn load(w: &mut Weights, prefix: &str, c: i64, eps: f64) -> Result<Self> {
        Ok(Self {
            weight: w.get(&format!("{prefix}.weight"), &[c])?,
            bias: w.get(&format!("{prefix}.bias"), &[c])?,
            mean: w.get(&format!("{prefix}.running_mean"), &[c])?,
            var: w.get(&format!("{prefix}.running_var"), &[c])?,
            eps,
        })
    }

    pub fn forward(&self, x: &Tensor) -> Tensor {
        x.batch_norm(
            Some(&self.weight),
            Some(&self.bias),
            Some(&self.mean),
            Some(&self.var),
            false,
            0.0,
            self.eps,
            false,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn missing_misshaped_and_unexpected_tensors_are_named() {
        let p = Path::new("w.safetensors");
        let list = vec![
            ("a.weight".to_string(), Tensor::zeros([2, 3], (Kind::Float, Device::Cpu))),
            ("extra".to_string(), Tensor::zeros([4], (Kind::Float, Device::Cpu))),
            ("bn.num_batches_tracked".to_string(), Tensor::zeros([], (Kind::Int64, Device::Cpu))),
        ];
        let mut w = Weights::from_tensors(p, list, Device::Cpu);
        let e = w.get("a.weight", &[3, 2]).unwrap_err().to_string();
        assert!(e.contains("'a.weight'") && e.contains("[2, 3]") && e.contains("[3, 2]"), "{e}");
        let e = w.get("b.weight", &[5]).unwrap_err().to_string();
        assert!(e.contains("'b.weight' is missing") && e.contains("[5]"), "{e}");
        assert_eq!(w.get("a.weight", &[2, 3]).unwrap().size(), [2, 3]);
        let e = w.finish().unwrap_err().to_string();
        assert!(e.contains("'extra'"), "{e}");
    }
}
