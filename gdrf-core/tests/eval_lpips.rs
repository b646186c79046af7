//! LPIPS v0.1 against the `lpips` package (scripts/reference/lpips_ref.py): for VGG16 and
//! AlexNet with a random backbone and the package's shipped heads, the distances and the
//! gradient of their sum with respect to x, at 64×64 and 48×40. The heads are the ones
//! scripts/convert_lpips_heads.py converts from the installed wheel, so the test also shows
//! that they are the package's.
mod common;

use common::{assert_close, read_tensors, run_python, TempDir};
use gdrf_core::pretrained::lpips::{Lpips, LpipsNet};
use std::time::Instant;
use tch::{Device, Kind, Tensor};

const SIZES: [&str; 2] = ["64x64", "48x40"];

/// Distances: float32 through the same libtorch kernels, so only summation order (batch
/// size, thread count) differs; 1e-4 relative with a floor of 1e-7 (about 1e-5 of the
/// smallest distance here) for the near-identical pair.
const D_RTOL: f64 = 1e-4;
const D_ATOL: f64 = 1e-7;
/// Gradients: the same relative tolerance, with an absolute floor of 1e-4 of the largest
/// gradient entry, for entries that are sums cancelling to near zero.
const G_RTOL: f64 = 1e-4;
const G_ATOL_FRACTION: f64 = 1e-4;

fn max_abs(t: &Tensor) -> f64 {
    f64::try_from(t.abs().max()).unwrap()
}

#[test]
fn matches_the_lpips_package() {
    let dir = TempDir::new("eval-lpips").unwrap();
    let out = dir.0.to_str().unwrap();
    let t0 = Instant::now();
    run_python("reference/lpips_ref.py", &[out]);
    run_python("convert_lpips_heads.py", &[out]);
    println!("python reference and conversion: {:.1} s", t0.elapsed().as_secs_f64());

    for net in [LpipsNet::Vgg16, LpipsNet::Alex] {
        let name = net.name();
        let t0 = Instant::now();
        let converted = dir.path(&format!("lpips-{name}-heads.safetensors"));
        // The converted heads are bit-identical to those the package loaded.
        let want_heads = read_tensors(&dir.path(&format!("{name}-heads.safetensors")));
        let got_heads = read_tensors(&converted);
        assert_eq!(got_heads.len(), want_heads.len(), "{name}: head count");
        for (k, want) in &want_heads {
            assert!(got_heads[k].equal(want), "{name}: converted {k} differs from the package's");
        }

        let lpips =
            Lpips::load(net, &dir.path(&format!("{name}-backbone.safetensors")), &converted, Device::Cpu).unwrap();
        let case = read_tensors(&dir.path(&format!("{name}-case.safetensors")));
        for size in SIZES {
            let x = case[&format!("x.{size}")].set_requires_grad(true);
            let y = &case[&format!("y.{size}")];
            let d = lpips.distance(&x, y).unwrap();
            let want_d = &case[&format!("expected.distance.{size}")];
            let rd = assert_close(&format!("{name} {size} distance"), &d, want_d, D_ATOL, D_RTOL);
            d.sum(Kind::Float).backward();
            let want_g = &case[&format!("expected.grad_x.{size}")];
            let g_atol = G_ATOL_FRACTION * max_abs(want_g);
            let rg = assert_close(&format!("{name} {size} grad x"), &x.grad(), want_g, g_atol, G_RTOL);
            println!(
                "{name} {size}: distance max |Δ| {:.2e} (rel {:.2e}, {rd:.3} of tolerance), grad max |Δ| {:.2e} of max |g| {:.2e} ({rg:.3} of tolerance)",
                max_abs(&(&d - want_d)),
                max_abs(&((&d - want_d) / want_d)),
                max_abs(&(x.grad() - want_g)),
                max_abs(want_g),
            );
            // Same image twice: exactly zero (both pass through the same deterministic kernels).
            let zero = lpips.distance(y, y).unwrap();
            assert_eq!(max_abs(&zero), 0.0, "{name} {size}: d(y, y) = {zero}");
        }
        println!("{name}: {:.1} s", t0.elapsed().as_secs_f64());
    }
}

#[test]
fn a_misshaped_file_names_the_file_the_tensor_and_both_shapes() {
    let dir = TempDir::new("eval-lpips-misshaped").unwrap();
    let zeros = |s: &[i64]| Tensor::zeros(s, (Kind::Float, Device::Cpu));
    let backbone = dir.path("alex-backbone.safetensors");
    let heads = dir.path("alex-heads.safetensors");
    let alex = [
        ("features.0", [64, 3, 11, 11]),
        ("features.3", [192, 64, 5, 5]),
        ("features.6", [384, 192, 3, 3]),
        ("features.8", [256, 384, 3, 3]),
        ("features.10", [256, 256, 3, 3]),
    ];
    let mut tensors = Vec::new();
    for (name, shape) in alex {
        tensors.push((format!("{name}.weight"), zeros(&shape)));
        tensors.push((format!("{name}.bias"), zeros(&shape[..1])));
    }
    let mut head_tensors: Vec<_> = [64, 192, 384, 256, 256]
        .iter()
        .enumerate()
        .map(|(i, &c)| (format!("lin{i}.model.1.weight"), zeros(&[1, c, 1, 1])))
        .collect();
    Tensor::write_safetensors(&head_tensors, &heads).unwrap();
    Tensor::write_safetensors(&tensors, &backbone).unwrap();
    Lpips::load(LpipsNet::Alex, &backbone, &heads, Device::Cpu).unwrap();

    // conv2 of AlexNet with a 3×3 kernel.
    tensors[2].1 = zeros(&[192, 64, 3, 3]);
    Tensor::write_safetensors(&tensors, &backbone).unwrap();
    let e = Lpips::load(LpipsNet::Alex, &backbone, &heads, Device::Cpu).unwrap_err().to_string();
    assert!(
        e.contains("alex-backbone.safetensors")
            && e.contains("'features.3.weight'")
            && e.contains("[192, 64, 3, 3]")
            && e.contains("[192, 64, 5, 5]"),
        "{e}"
    );

    // A VGG-sized head.
    tensors[2].1 = zeros(&[192, 64, 5, 5]);
    Tensor::write_safetensors(&tensors, &backbone).unwrap();
    head_tensors[1].1 = zeros(&[1, 128, 1, 1]);
    Tensor::write_safetensors(&head_tensors, &heads).unwrap();
    let e = Lpips::load(LpipsNet::Alex, &backbone, &heads, Device::Cpu).unwrap_err().to_string();
    assert!(
        e.contains("alex-heads.safetensors")
            && e.contains("'lin1.model.1.weight'")
            && e.contains("[1, 128, 1, 1]")
            && e.contains("[1, 192, 1, 1]"),
        "{e}"
    );
}
