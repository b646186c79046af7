//! Distances between two sets of image features, in float64: the Fréchet distance (FID's
//! formula on any features) and the kernel distance (KID: unbiased MMD² with the cubic
//! polynomial kernel, averaged over random subsets).
use crate::rng::{Purpose, StepRng};
use crate::{Error, Result};
use tch::{Device, Kind, Tensor};

/// Offset added to both covariances' diagonals when a set has no more samples than the
/// feature dimension (pytorch-fid's `eps` for its singular case).
pub const FD_EPS: f64 = 1e-6;

/// A Fréchet distance and how it was obtained.
#[derive(Debug, Clone, PartialEq)]
pub struct Frechet {
    pub value: f64,
    /// Set when a covariance was rank-deficient and [`FD_EPS`]·I was added: the value is
    /// then a regularised estimate and not comparable with full-rank ones.
    pub warning: Option<String>,
}

/// Mean `(d,)` and unbiased covariance `(d, d)` of `(n, d)` features, float64.
pub fn mean_cov(x: &Tensor) -> (Tensor, Tensor) {
    let x = x.to_kind(Kind::Double);
    let n = x.size()[0];
    let mu = x.mean_dim(0, false, Kind::Double);
    let c = &x - &mu;
    let cov = c.transpose(0, 1).matmul(&c) / ((n - 1).max(1) as f64);
    (mu, cov)
}

/// Symmetric PSD square root through the eigendecomposition (eigenvalues clamped at 0:
/// round-off makes the smallest ones slightly negative).
fn sqrt_psd(a: &Tensor) -> Tensor {
    let (vals, vecs) = ((a + a.transpose(0, 1)) / 2.0).linalg_eigh("L");
    let s = vals.clamp_min(0.0).sqrt();
    (&vecs * s.unsqueeze(0)).matmul(&vecs.transpose(0, 1))
}

/// ‖μ₁ − μ₂‖² + tr Σ₁ + tr Σ₂ − 2 tr √(Σ₁ Σ₂), with tr √(Σ₁Σ₂) computed as the sum of the
/// square roots of the eigenvalues of √Σ₁ Σ₂ √Σ₁ — symmetric and PSD, so the result is
/// real without discarding an imaginary part (scipy's `sqrtm(Σ₁Σ₂)` of pytorch-fid gives
/// the same value when the product is well conditioned).
pub fn frechet_from_stats(mu1: &Tensor, cov1: &Tensor, mu2: &Tensor, cov2: &Tensor) -> Result<f64> {
    let d = mu1.size()[0];
    for (name, t, want) in [("mu2", mu2, vec![d]), ("cov1", cov1, vec![d, d]), ("cov2", cov2, vec![d, d])] {
        if t.size() != want {
            return Err(Error::Shape(format!("Fréchet distance: {name} has shape {:?}, expected {want:?}", t.size())));
        }
    }
    let [mu1, mu2, cov1, cov2] = [mu1, mu2, cov1, cov2].map(|t| t.to_kind(Kind::Double));
    let diff = f64::try_from((&mu1 - &mu2).square().sum(Kind::Double))?;
    let s1 = sqrt_psd(&cov1);
    let m = s1.matmul(&cov2).matmul(&s1);
    let vals = ((&m + m.transpose(0, 1)) / 2.0).linalg_eigvalsh("L");
    let tr_sqrt = f64::try_from(vals.clamp_min(0.0).sqrt().sum(Kind::Double))?;
    let tr = f64::try_from(cov1.trace() + cov2.trace())?;
    let value = diff + tr - 2.0 * tr_sqrt;
    if !value.is_finite() {
        return Err(Error::Invalid("Fréchet distance is not finite: the features contain NaN or infinity".into()));
    }
    // Round-off can leave −1e-12 for identical sets.
    Ok(value.max(0.0))
}

fn check_features(name: &str, x: &Tensor) -> Result<()> {
    let s = x.size();
    if s.len() != 2 || s[0] < 2 {
        return Err(Error::Shape(format!("{name}: expected (N ≥ 2, D) features, got shape {s:?}")));
    }
    if !bool::try_from(x.isfinite().all())? {
        return Err(Error::Invalid(format!("{name}: features contain NaN or infinity")));
    }
    Ok(())
}

/// Fréchet distance between feature sets `a: (n, d)` and `b: (m, d)`. When n ≤ d or m ≤ d
/// the covariances are singular: [`FD_EPS`]·I is added to both and the result carries a
/// warning saying so.
pub fn frechet(a: &Tensor, b: &Tensor) -> Result<Frechet> {
    check_features("first feature set", a)?;
    check_features("second feature set", b)?;
    let (n, m, d) = (a.size()[0], b.size()[0], a.size()[1]);
    if b.size()[1] != d {
        return Err(Error::Shape(format!("feature sets have different widths: {d} and {}", b.size()[1])));
    }
    let (mu1, mut c1) = mean_cov(a);
    let (mu2, mut c2) = mean_cov(b);
    let warning = (n <= d || m <= d).then(|| {
        let eye = Tensor::eye(d, (Kind::Double, c1.device())) * FD_EPS;
        c1 = &c1 + &eye;
        c2 = &c2 + &eye;
        format!(
            "Fréchet distance from {n} and {m} samples of {d}-d features: the covariances are singular \
             (fewer samples than dimensions + 1), so {FD_EPS:e}·I was added to both; \
             the value is a regularised estimate, not comparable with full-rank ones"
        )
    });
    Ok(Frechet { value: frechet_from_stats(&mu1, &c1, &mu2, &c2)?, warning })
}

/// Unbiased MMD² between `x: (m, d)` and `y: (m, d)` with k(u, v) = (u·v / d + 1)³.
fn mmd2_cubic(x: &Tensor, y: &Tensor) -> f64 {
    let (m, d) = (x.size()[0] as f64, x.size()[1] as f64);
    let k = |a: &Tensor, b: &Tensor| (a.matmul(&b.transpose(0, 1)) / d + 1.0).pow_tensor_scalar(3);
    let kxx = k(x, x);
    let kyy = k(y, y);
    let kxy = k(x, y);
    let off = |t: &Tensor| f64::try_from(t.sum(Kind::Double) - t.diagonal(0, 0, 1).sum(Kind::Double)).unwrap();
    (off(&kxx) + off(&kyy)) / (m * (m - 1.0)) - 2.0 * f64::try_from(kxy.sum(Kind::Double)).unwrap() / (m * m)
}

/// A kernel distance: the mean and standard deviation over subsets.
#[derive(Debug, Clone, PartialEq)]
pub struct Kernel {
    pub mean: f64,
    pub std: f64,
    pub subsets: usize,
    pub subset_size: i64,
}

/// KID on explicit subsets: each pair gives row indices into `a` and `b` (same length).
pub fn kernel_on_subsets(a: &Tensor, b: &Tensor, subsets: &[(Vec<i64>, Vec<i64>)]) -> Result<Kernel> {
    check_features("first feature set", a)?;
    check_features("second feature set", b)?;
    if a.size()[1] != b.size()[1] {
        return Err(Error::Shape(format!("feature sets have different widths: {} and {}", a.size()[1], b.size()[1])));
    }
    let (a, b) = (a.to_kind(Kind::Double), b.to_kind(Kind::Double));
    let mut vals = Vec::with_capacity(subsets.len());
    for (ia, ib) in subsets {
        if ia.len() != ib.len() || ia.len() < 2 {
            return Err(Error::Invalid(
                "kernel distance: each subset pair needs two equal lists of ≥ 2 indices".into(),
            ));
        }
        let pick = |t: &Tensor, i: &[i64]| t.index_select(0, &Tensor::from_slice(i).to_device(t.device()));
        vals.push(mmd2_cubic(&pick(&a, ia), &pick(&b, ib)));
    }
    if vals.is_empty() {
        return Err(Error::Invalid("kernel distance: no subsets".into()));
    }
    let n = vals.len() as f64;
    let mean = vals.iter().sum::<f64>() / n;
    let std = (vals.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n).sqrt();
    Ok(Kernel { mean, std, subsets: vals.len(), subset_size: subsets[0].0.len() as i64 })
}

/// KID as clean-fid and torch-fidelity compute it: `subsets` random subsets of
/// min(n, m, `max_subset_size`) rows of each set, drawn without replacement from `seed`.
pub fn kernel(a: &Tensor, b: &Tensor, subsets: usize, max_subset_size: i64, seed: u64) -> Result<Kernel> {
    let (n, m) = (a.size()[0], b.size()[0]);
    let size = n.min(m).min(max_subset_size);
    let mut rng = StepRng::new(seed, 0, Purpose::EvalSubsets, Kind::Double, Device::Cpu);
    let mut draw = |total: i64| -> Vec<i64> {
        // Partial Fisher–Yates: the first `size` entries of a random permutation.
        let mut idx: Vec<i64> = (0..total).collect();
        let r = rng.u64s(size as usize);
        for (i, ri) in r.iter().enumerate() {
            let j = i + (ri % (total as u64 - i as u64)) as usize;
            idx.swap(i, j);
        }
        idx.truncate(size as usize);
        idx
    };
    let pairs: Vec<_> = (0..subsets).map(|_| (draw(n), draw(m))).collect();
    kernel_on_subsets(a, b, &pairs)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identical_sets_are_at_zero_and_a_shift_is_its_square() {
        let a = Tensor::randn([200, 8], (Kind::Double, Device::Cpu));
        assert!(frechet(&a, &a).unwrap().value.abs() < 1e-9);
        // A constant shift of every feature by 0.5 moves only the means: FD = 8 · 0.25.
        let fd = frechet(&a, &(&a + 0.5)).unwrap();
        assert!((fd.value - 2.0).abs() < 1e-9, "{fd:?}");
        assert!(fd.warning.is_none());
    }

    #[test]
    fn few_samples_warn_and_stay_finite() {
        let a = Tensor::randn([5, 16], (Kind::Double, Device::Cpu));
        let b = Tensor::randn([7, 16], (Kind::Double, Device::Cpu));
        let fd = frechet(&a, &b).unwrap();
        assert!(fd.value.is_finite() && fd.value > 0.0);
        assert!(fd.warning.as_deref().unwrap().contains("singular"));
        let bad = Tensor::from_slice(&[1.0, f64::NAN, 0.0, 1.0]).view([2, 2]);
        assert!(frechet(&bad, &bad).unwrap_err().to_string().contains("NaN"));
    }

    #[test]
    fn kernel_distance_of_a_set_with_itself_is_near_zero() {
        let a = Tensor::randn([300, 10], (Kind::Double, Device::Cpu));
        let b = Tensor::randn([300, 10], (Kind::Double, Device::Cpu)) + 1.0;
        let same = kernel(&a, &a, 20, 100, 1).unwrap();
        let far = kernel(&a, &b, 20, 100, 1).unwrap();
        assert!(same.mean.abs() < 0.05 * far.mean, "{same:?} vs {far:?}");
        assert_eq!(far.subset_size, 100);
    }
}
