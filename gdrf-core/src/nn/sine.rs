//! The sine of the SIREN layers. libtorch computes float32 `sin` and `cos` on the CPU with
//! MKL's VML; SLEEF's AVX2 functions (which libtorch itself uses for its bfloat16 and half
//! sines, and exports) take 0.8–1.4 ns an element where MKL takes 2.3–4.0 ns (one core of
//! the project's AMD EPYC; docs/benchmarks.md, its paragraph "The sine"). The SIREN layers' sines and their
//! derivatives were a fifth of a training step on the project's 2-core AMD EPYC, so float32
//! CPU tensors go through SLEEF: the bridge in `sine.cpp`, an autograd function whose
//! derivatives are each other's, so gradients of every order stay exact. Every other dtype
//! and device, and a CPU without AVX2 and FMA, use libtorch's own.
//!
//! Accuracy: SLEEF's 3.5-ULP functions for |x| < 125 000 (within 2.1e-7 of the true value),
//! its 1.0-ULP ones beyond; libtorch's MKL path is within about 1 ULP.
use std::cell::Cell;
use std::ffi::{c_char, c_int, c_void, CStr};
use tch::{Device, Kind, Tensor};

thread_local! {
    /// Set on the thread running [`with_libtorch_sine`].
    static LIBTORCH_SINE: Cell<bool> = const { Cell::new(false) };
}

extern "C" {
    fn gdrf_sin(x: *mut c_void, err: *mut c_char, err_len: usize) -> *mut c_void;
    fn gdrf_sine_vectorised() -> c_int;
}

/// `sin(x)` elementwise, any shape, differentiable to any order (its derivative, cos,
/// goes through SLEEF as well).
pub fn sin(x: &Tensor) -> Tensor {
    if x.device() != Device::Cpu || x.kind() != Kind::Float || LIBTORCH_SINE.get() {
        return x.sin();
    }
    let mut err = [0 as c_char; 512];
    // SAFETY: `x` is a live float32 CPU tensor; the bridge only reads it and returns a new
    // at::Tensor* (owned by the returned Tensor) or NULL with a NUL-terminated message.
    let out = unsafe { gdrf_sin(x.as_ptr() as *mut c_void, err.as_mut_ptr(), err.len()) };
    if out.is_null() {
        // As tch's own elementwise calls do, a libtorch failure here (out of memory) panics.
        let msg = unsafe { CStr::from_ptr(err.as_ptr()) }.to_string_lossy();
        panic!("sin: {msg}");
    }
    // SAFETY: a fresh at::Tensor* from the bridge, owned from here on.
    unsafe { Tensor::from_ptr(out.cast()) }
}

/// Runs `f` with every sine this thread asks for through libtorch's own, as before SLEEF:
/// the step benchmark's comparison (`gdrf-bench step`). Other threads are not affected.
pub fn with_libtorch_sine<T>(f: impl FnOnce() -> T) -> T {
    struct Restore;
    impl Drop for Restore {
        fn drop(&mut self) {
            LIBTORCH_SINE.set(false);
        }
    }
    LIBTORCH_SINE.set(true);
    let _restore = Restore;
    f()
}

/// Whether float32 CPU sines run through SLEEF's AVX2 code on this machine.
pub fn vectorised() -> bool {
    // SAFETY: reads a flag computed once from CPUID.
    unsafe { gdrf_sine_vectorised() != 0 }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Arguments that cover the SIREN layers' range, the large ones where range reduction
    /// matters, signed zeros, subnormals and the non-finite values.
    fn arguments() -> Tensor {
        let edge = Tensor::from_slice(&[
            0.0f32,
            -0.0,
            1e-40,
            -1e-40,
            f32::MIN_POSITIVE,
            std::f32::consts::PI,
            -std::f32::consts::FRAC_PI_2,
            1e4,
            -12345.678,
            1e6,
            3e7,
            f32::MAX,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
        ]);
        tch::manual_seed(3);
        let bulk = (Tensor::rand([100_003], (Kind::Float, Device::Cpu)) - 0.5) * 400.0;
        // Up to the 3.5-ULP functions' bound and past it.
        let wide = (Tensor::rand([10_001], (Kind::Float, Device::Cpu)) - 0.5) * 2.6e5;
        Tensor::cat(&[edge, bulk, wide], 0)
    }

    fn assert_close_to_f64(got: &Tensor, want: &Tensor) {
        let got = got.to_kind(Kind::Double);
        // NaN exactly where the true value is NaN (±∞ and NaN inputs).
        assert!(got.isnan().equal(&want.isnan()), "NaN pattern differs");
        let finite = want.isfinite();
        let err = (got.masked_select(&finite) - want.masked_select(&finite)).abs().max().double_value(&[]);
        // 3.5 ULP, and |value| ≤ 1 puts an ULP at ≤ 2⁻²⁴.
        assert!(err <= 3.5 * 2f64.powi(-24), "max |error| {err:e}");
    }

    /// The gradient of Σ sin(x): cos(x), through the bridge's cosine.
    fn cos_by_gradient(x: &Tensor) -> Tensor {
        let x = x.detach().set_requires_grad(true);
        Tensor::run_backward(&[sin(&x).sum(Kind::Float)], &[&x], false, false).remove(0)
    }

    #[test]
    fn sine_and_cosine_are_accurate_over_the_whole_float_range() {
        let x = arguments();
        let x64 = x.to_kind(Kind::Double);
        assert_close_to_f64(&sin(&x), &x64.sin());
        assert_close_to_f64(&cos_by_gradient(&x), &x64.cos());
        // Signs of zero kept, as libtorch's sin does.
        let z: Vec<f32> = Vec::try_from(&sin(&Tensor::from_slice(&[0.0f32, -0.0]))).unwrap();
        assert_eq!(z[0].to_bits(), 0.0f32.to_bits());
        assert_eq!(z[1].to_bits(), (-0.0f32).to_bits());
    }

    #[test]
    fn any_shape_and_stride_and_the_vector_tail() {
        // Every length 0..=19 (all tails of an 8-wide vector), a transposed view, and an
        // expanded one (zero strides).
        for n in 0..=19 {
            let x = Tensor::arange(n, (Kind::Float, Device::Cpu)) * 0.7 - 3.0;
            assert!(sin(&x).allclose(&x.sin(), 1e-6, 1e-6, false), "length {n}");
            assert!(cos_by_gradient(&x).allclose(&x.cos(), 1e-6, 1e-6, false), "length {n}");
        }
        let x = Tensor::rand([37, 11], (Kind::Float, Device::Cpu)).transpose(0, 1);
        let y = sin(&x);
        assert_eq!(y.size(), vec![11, 37]);
        assert!(y.allclose(&x.sin(), 1e-6, 1e-6, false));
        let e = Tensor::from_slice(&[0.25f32, 2.0]).view([2, 1]).expand([2, 5], false);
        assert!(sin(&e).allclose(&e.sin(), 1e-6, 1e-6, false));
        // Other dtypes go through libtorch unchanged.
        let d = Tensor::from_slice(&[0.5f64, 1.5]);
        assert!(sin(&d).equal(&d.sin()));
        assert_eq!(sin(&d).kind(), Kind::Double);
        let h = d.to_kind(Kind::BFloat16);
        assert!(sin(&h).equal(&h.sin()));
    }

    #[test]
    fn derivatives_of_the_first_three_orders_are_exact() {
        tch::manual_seed(5);
        let x = ((Tensor::rand([2, 300], (Kind::Float, Device::Cpu)) - 0.5) * 60.0).set_requires_grad(true);
        let w = Tensor::rand([2, 300], (Kind::Float, Device::Cpu));
        let y = sin(&x);
        assert!(y.requires_grad());
        let d1 = Tensor::run_backward(&[(&y * &w).sum(Kind::Float)], &[&x], true, true).remove(0);
        let d2 = Tensor::run_backward(&[d1.sum(Kind::Float)], &[&x], true, true).remove(0);
        let d3 = Tensor::run_backward(&[d2.sum(Kind::Float)], &[&x], false, false).remove(0);
        // w·cos, −w·sin, −w·cos, in float64.
        let (x64, w64) = (x.detach().to_kind(Kind::Double), w.to_kind(Kind::Double));
        for (got, want, order) in [(d1, x64.cos() * &w64, 1), (d2, -x64.sin() * &w64, 2), (d3, -x64.cos() * &w64, 3)] {
            let diff = (got.to_kind(Kind::Double) - &want).abs().max().double_value(&[]);
            // 3.5 ULP of the sine, and the product with w rounded once more.
            assert!(diff <= 3e-7, "order {order}: max |error| {diff:e}");
        }
        // Under no_grad nothing is recorded.
        assert!(!tch::no_grad(|| sin(&x)).requires_grad());
    }

    #[test]
    fn the_benchmark_switch_gives_libtorchs_sine_and_restores_the_default() {
        let x = (Tensor::rand([4096], (Kind::Float, Device::Cpu)) - 0.5) * 300.0;
        let (plain, elsewhere) = with_libtorch_sine(|| {
            // Another thread meanwhile keeps the default.
            let y = x.copy();
            let other = std::thread::spawn(move || sin(&y)).join().unwrap();
            (sin(&x), other)
        });
        assert!(plain.equal(&x.sin()), "libtorch's sine, bit for bit");
        if vectorised() {
            assert!(!elsewhere.equal(&x.sin()), "the switch reached another thread");
        }
        assert!(sin(&x).allclose(&x.sin(), 0.0, 3.5 * 2f64.powi(-24), false));
        if vectorised() {
            // SLEEF again after the switch: not libtorch's bits everywhere.
            assert!(!sin(&x).equal(&x.sin()), "the switch was not restored");
        }
    }

    #[test]
    fn this_machine_takes_the_vector_path_where_it_has_avx2() {
        #[cfg(target_arch = "x86_64")]
        assert_eq!(vectorised(), std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma"));
        #[cfg(not(target_arch = "x86_64"))]
        assert!(!vectorised());
    }
}
