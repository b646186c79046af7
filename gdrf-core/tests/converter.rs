//! scripts/convert_official_checkpoint.py on files shaped like the authors' release:
//! the EMA shadow replaces the weights in the release's parameter order, and bad inputs
//! fail with a message that names the file.
mod common;

use common::{python, read_tensors, repo_root, run_python, TempDir};
use gdrf_core::checkpoint::load_generator;
use std::process::Command;
use tch::{Device, Kind};

fn convert(args: &[&str]) -> (bool, String) {
    let out = Command::new(python())
        .arg(repo_root().join("scripts/convert_official_checkpoint.py"))
        .args(args)
        .output()
        .unwrap();
    (out.status.success(), String::from_utf8_lossy(&out.stderr).into_owned())
}

#[test]
fn ema_weights_replace_the_raw_weights() {
    let dir = TempDir::new("convert-ema").unwrap();
    let d = |n: &str| dir.path(n).to_str().unwrap().to_string();
    run_python("reference/make_release_checkpoint.py", &["--out", &d("")]);
    let (ok, err) =
        convert(&[&d("generator.pth"), &d("chair.safetensors"), "--ema", &d("ema.pth"), "--camera", "chair"]);
    assert!(ok, "{err}");
    let g = load_generator(&dir.path("chair.safetensors"), Device::Cpu, Kind::Float).unwrap();
    assert_eq!(g.header.camera, Some(gdrf_core::CameraConfig::chair()));
    assert_eq!(g.header.generator, gdrf_core::GeneratorConfig::default());
    let want = read_tensors(&dir.path("expected_ema.safetensors"));
    let vars = g.vs.variables();
    assert_eq!(want.len(), vars.len());
    for (name, t) in &want {
        assert!(vars[name].equal(t), "{name} differs from the EMA shadow");
    }
}

#[test]
fn bad_inputs_name_the_file() {
    let dir = TempDir::new("convert-bad").unwrap();
    let d = |n: &str| dir.path(n).to_str().unwrap().to_string();
    run_python("reference/make_release_checkpoint.py", &["--out", &d("")]);
    std::fs::write(dir.path("junk.pth"), b"not a pickle").unwrap();
    let (ok, err) = convert(&[&d("junk.pth"), &d("out.safetensors")]);
    assert!(!ok && err.contains("junk.pth") && err.contains("torch.load"), "{err}");
    let (ok, err) = convert(&[&d("generator.pth"), &d("out.safetensors"), "--ema", &d("ema_short.pth")]);
    assert!(!ok && err.contains("ema_short.pth") && err.contains("47 shadow parameters"), "{err}");
    assert!(!dir.path("out.safetensors").exists(), "a failed conversion left an output file");
}

/// Mutated release files (scripts/reference/fuzz_converter.py, a fixed seed): each converts
/// or is refused with exit 1 and a message naming the file; no other exception escapes and
/// no temporary file stays beside the output.
#[test]
fn mutated_release_files_convert_or_are_refused_naming_the_file() {
    let dir = TempDir::new("convert-fuzz").unwrap();
    let out = Command::new(python())
        .arg(repo_root().join("scripts/reference/fuzz_converter.py"))
        .args(["--dir", dir.0.to_str().unwrap(), "--cases", "100"])
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&out.stdout);
    println!("{said}");
    assert!(out.status.success(), "{said}\n{}", String::from_utf8_lossy(&out.stderr));
    let counts: serde_json::Value = serde_json::from_str(&said).unwrap();
    assert_eq!(counts["cases"], 100);
    assert!(counts["refused_naming_the_file"].as_u64().unwrap() > 0, "{said}");
}

/// A file holding a pickled module (what the release saves) is opened only with
/// --trust-pickle: unpickling it runs code from the file.
#[test]
fn a_pickled_module_needs_trust_pickle() {
    let dir = TempDir::new("convert-pickle").unwrap();
    let module = dir.path("module.pth");
    let made = Command::new(python())
        .args(["-c", "import sys, torch; torch.save(torch.nn.Linear(2, 3), sys.argv[1])"])
        .arg(&module)
        .status()
        .unwrap();
    assert!(made.success());
    let out = dir.path("out.safetensors");
    let (ok, err) = convert(&[module.to_str().unwrap(), out.to_str().unwrap()]);
    assert!(!ok && err.contains("module.pth") && err.contains("--trust-pickle"), "{err}");
    let (ok, err) = convert(&[module.to_str().unwrap(), out.to_str().unwrap(), "--trust-pickle"]);
    // Opened: a Linear is no GDRF generator, which is the error now.
    assert!(!ok && !err.contains("--trust-pickle") && err.contains("missing tensor"), "{err}");
    assert!(!out.exists());
}
