//! The opacity term: each generated ray is asked to be object or background.
use tch::Tensor;

/// Opacities are clamped to [ε, 1 − ε] before the logarithms, so that a ray that is exactly
/// empty or exactly opaque gives a finite value and gradient (the term's slope there is at
/// most ln((1 − ε)/ε) ≈ 13.8 per ray).
pub const OPACITY_EPS: f64 = 1e-6;

/// The mean binary entropy, in nats, of opacities `alpha` (any shape, in [0, 1]):
/// mean of −α·ln α − (1 − α)·ln(1 − α) over every element, computed in float32 or wider.
/// It is ln 2 at α = ½ and 0 at α = 0 or 1 (up to [`OPACITY_EPS`]); its gradient pushes
/// each α away from ½, toward the nearer end.
pub fn opacity_entropy(alpha: &Tensor) -> Tensor {
    let a = crate::render::wide(alpha).clamp(OPACITY_EPS, 1.0 - OPACITY_EPS);
    let b = a.neg() + 1.0;
    let h = -(&a * a.log()) - &b * b.log();
    h.mean(h.kind())
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Kind;

    #[test]
    fn entropy_is_ln2_at_a_half_and_zero_at_the_ends() {
        let h = |v: &[f64]| opacity_entropy(&Tensor::from_slice(v)).double_value(&[]);
        assert!((h(&[0.5]) - std::f64::consts::LN_2).abs() < 1e-12);
        let eps = OPACITY_EPS;
        let end = -(eps * eps.ln()) - (1.0 - eps) * (1.0 - eps).ln();
        assert!((h(&[0.0, 1.0]) - end).abs() < 1e-12, "{}", h(&[0.0, 1.0]));
        // The mean over elements, at a value known in closed form: H(0.25) = ln 4 − ¾ ln 3.
        let quarter = 4f64.ln() - 0.75 * 3f64.ln();
        assert!((h(&[0.25, 0.75, 0.5]) - (2.0 * quarter + std::f64::consts::LN_2) / 3.0).abs() < 1e-12);
    }

    #[test]
    fn gradient_pushes_away_from_a_half_and_is_finite_at_the_ends() {
        let a = Tensor::from_slice(&[0.0f32, 0.2, 0.5, 0.8, 1.0]).set_requires_grad(true);
        opacity_entropy(&a).backward();
        let g = Vec::<f32>::try_from(a.grad()).unwrap();
        // dH/dα = ln((1 − α)/α) / n: descent lowers α below ½ and raises it above.
        let n = 5.0f64;
        for (i, (alpha, expected)) in
            [(0.2f64, (0.8f64 / 0.2).ln() / n), (0.5, 0.0), (0.8, (0.2f64 / 0.8).ln() / n)].into_iter().enumerate()
        {
            let got = g[i + 1] as f64;
            assert!((got - expected).abs() < 1e-6 + 1e-5 * expected.abs(), "α {alpha}: {got} against {expected}");
        }
        // Clamped ends: no gradient flows through the clamp, and nothing is NaN.
        assert!(g.iter().all(|v| v.is_finite()), "{g:?}");
        assert_eq!((g[0], g[4]), (0.0, 0.0));
    }

    #[test]
    fn half_precision_is_integrated_in_float32() {
        let a = Tensor::from_slice(&[0.3f32, 0.9]).to_kind(Kind::BFloat16);
        let h = opacity_entropy(&a);
        assert_eq!(h.kind(), Kind::Float);
        let wide = opacity_entropy(&a.to_kind(Kind::Float));
        assert_eq!(h.double_value(&[]), wide.double_value(&[]));
    }
}
