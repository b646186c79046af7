//! FID's Inception-v3 against pytorch-fid itself (scripts/reference/inception_ref.py builds
//! pytorch-fid's `InceptionV3([3])` with random weights and BatchNorm statistics): pool3
//! features of inputs smaller than, equal to, larger than 299² and non-square; and the
//! errors of bad weight files.
mod common;

use common::{assert_close, read_tensors, run_python, TempDir};
use gdrf_core::pretrained::inception::{InceptionV3, FEATURE_DIM};
use gdrf_core::pretrained::weights::Weights;
use gdrf_core::Error;
use std::path::Path;
use tch::{Device, Kind, Tensor};

#[test]
fn features_match_pytorch_fid() {
    let dir = TempDir::new("eval-inception").unwrap();
    run_python("reference/inception_ref.py", &[dir.0.to_str().unwrap()]);
    let net = InceptionV3::load(&dir.path("weights.safetensors"), Device::Cpu).unwrap();
    let case = read_tensors(&dir.path("case.safetensors"));
    let mut names: Vec<_> = case.keys().filter_map(|k| k.strip_prefix("input.")).collect();
    names.sort();
    assert_eq!(names.len(), 4, "case has {names:?}");
    for name in names {
        let x = &case[&format!("input.{name}")];
        let want = &case[&format!("expected.{name}")];
        let got = net.features_from_signed(x).unwrap();
        assert_eq!(got.size(), [x.size()[0], FEATURE_DIM]);
        assert_eq!(got.kind(), Kind::Float);
        let scale = f64::try_from(want.abs().max()).unwrap();
        let abs = f64::try_from((&got - want).abs().max()).unwrap();
        let rel = f64::try_from(((&got - want).abs() / want.abs().clamp_min(1e-30)).max()).unwrap();
        println!("{name}: {:?}, max|want| {scale:.3}, max|Δ| {abs:.3e}, max rel {rel:.3e}", x.size());
        // Each feature is a mean of ReLU'd, batch-normalised sums of up to 2048·9 float32
        // products, so rounding in it is relative to the activations' scale, not to the
        // feature's own value: a feature near 0 (a channel that is mostly cut off by the
        // ReLU) carries an absolute error of a few float32 ulps of the scale. atol is set
        // at 1e-6 of the batch's largest feature, i.e. ~8 ulps.
        assert_close(&format!("features {name}"), &got, want, 1e-6 * scale, 1e-4);
    }
    let e = net.features_from_signed(&Tensor::zeros([3, 64, 64], (Kind::Float, Device::Cpu))).unwrap_err();
    assert!(matches!(e, Error::Shape(_)), "{e}");
}

type Named = Vec<(String, Tensor)>;

#[test]
fn bad_weight_files_are_named() {
    let dir = TempDir::new("eval-inception-weights").unwrap();
    run_python("reference/inception_ref.py", &[dir.0.to_str().unwrap(), "--weights-only"]);
    let good = read_tensors(&dir.path("weights.safetensors"));
    // The good tensors, edited.
    let with = |edit: &dyn Fn(&mut Named)| {
        let mut list: Named = good.iter().map(|(k, v)| (k.clone(), v.shallow_clone())).collect();
        edit(&mut list);
        list
    };

    // Mixed_7c's pool conv with Mixed_7b's input width (the two E blocks confused).
    let bad = "blocks.3.2.branch_pool.conv.weight";
    let path = dir.path("misshaped.safetensors");
    let list = with(&|l| {
        l.iter_mut().find(|(k, _)| k == bad).unwrap().1 = Tensor::zeros([192, 1280, 1, 1], (Kind::Float, Device::Cpu))
    });
    Tensor::write_safetensors(&list, &path).unwrap();
    let e = InceptionV3::load(&path, Device::Cpu).err().expect("a mis-shaped tensor must be an error").to_string();
    assert!(
        e.contains(&format!("'{bad}'")) && e.contains("[192, 1280, 1, 1]") && e.contains("[192, 2048, 1, 1]"),
        "{e}"
    );

    let missing = "blocks.2.5.branch7x7dbl_4.bn.running_var";
    let list = with(&|l| l.retain(|(k, _)| k != missing));
    let e =
        InceptionV3::from_weights(Weights::from_tensors(Path::new("w"), list, Device::Cpu)).err().unwrap().to_string();
    assert!(e.contains(&format!("'{missing}' is missing")) && e.contains("[160]"), "{e}");

    // A torchvision Inception3 state dict has the classifier: not this network's file.
    let list = with(&|l| l.push(("fc.weight".into(), Tensor::zeros([1008, 2048], (Kind::Float, Device::Cpu)))));
    let e =
        InceptionV3::from_weights(Weights::from_tensors(Path::new("w"), list, Device::Cpu)).err().unwrap().to_string();
    assert!(e.contains("unexpected tensor 'fc.weight'"), "{e}");

    InceptionV3::from_weights(Weights::from_tensors(Path::new("w"), with(&|_| {}), Device::Cpu)).unwrap();
}

#[test]
fn missing_file_is_an_error() {
    let path = std::env::temp_dir().join("gdrf-no-such-inception.safetensors");
    let e = InceptionV3::load(&path, Device::Cpu).err().expect("a missing file must be an error");
    assert!(matches!(e, Error::Io { .. }) && e.to_string().contains("gdrf-no-such-inception"), "{e}");
}
