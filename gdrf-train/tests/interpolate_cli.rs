//! `gdrf-train interpolate` writes the blend its flags ask for, with both sources in its
//! header, and refuses bad input by name.
#[path = "../../gdrf-core/tests/common/mod.rs"]
mod common;

use common::{repo_root, TempDir};
use gdrf_core::checkpoint::{load_generator, save_generator};
use std::process::Command;
use tch::{Device, Kind};

fn interpolate(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_gdrf-train"))
        .current_dir(repo_root())
        .arg("interpolate")
        .args(args)
        .output()
        .unwrap()
}

/// chairs-tiny-ms (FROM) blended at t = 0.25 with a copy of it whose every parameter is
/// doubled (TO) gives 0.75·w + 0.25·2w = 1.25·w (with FROM and TO swapped it would be 1.75·w),
/// and the header keeps what both sources record: their steps under `from.`/`to.`
/// (chairs-tiny-ms stopped at step 5 211), and the training resolution and samples per ray
/// they share (it last trained at 32², 12 + 12).
#[test]
fn interpolate_writes_the_blend_its_flags_ask_for() {
    let dir = TempDir::new("interpolate").unwrap();
    let ms = "models/chairs-tiny-ms/generator.safetensors";
    let source = load_generator(&repo_root().join(ms), Device::Cpu, Kind::Float).unwrap();
    let doubled = dir.path("doubled.safetensors");
    {
        let copy = load_generator(&repo_root().join(ms), Device::Cpu, Kind::Float).unwrap();
        tch::no_grad(|| {
            for (_, mut v) in copy.vs.variables() {
                let _ = v.f_mul_scalar_(2.0).unwrap();
            }
        });
        save_generator(&doubled, &copy.vs, &copy.header).unwrap();
    }
    let out = dir.path("blend.safetensors");
    let run =
        interpolate(&["--from", ms, "--to", doubled.to_str().unwrap(), "--t", "0.25", "--out", out.to_str().unwrap()]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let made = load_generator(&out, Device::Cpu, Kind::Float).unwrap();
    for (key, want) in [("resolution", "32"), ("samples_per_ray", "24"), ("step", "5211")] {
        for prefix in ["from.", "to."] {
            assert_eq!(
                made.header.info.get(&format!("{prefix}{key}")).map(String::as_str),
                Some(want),
                "{prefix}{key}"
            );
        }
    }
    for (key, want) in [("resolution", "32"), ("samples_per_ray", "24")] {
        assert_eq!(made.header.info.get(key).map(String::as_str), Some(want), "{key}");
    }
    let want = source.vs.variables();
    let got = made.vs.variables();
    assert_eq!(got.len(), want.len());
    assert_eq!(got.len(), 48);
    for (name, t) in got {
        let expected = &want[&name] * 1.25;
        assert!(t.allclose(&expected, 1e-6, 1e-7, false), "{name} is not 1.25 × chairs-tiny-ms's");
    }
}

#[test]
fn interpolate_refuses_bad_input_by_name() {
    let dir = TempDir::new("interpolate-errors").unwrap();
    let out = dir.path("x.safetensors");
    let ms = "models/chairs-tiny-ms/generator.safetensors";
    for (t, to, expected) in [
        ("1.5", ms, "t is 1.5, expected a weight in [0, 1]"),
        ("0.5", "models/chairs-probe/probe.safetensors", "probe.safetensors"),
        ("0.5", "models/no-such/generator.safetensors", "models/no-such/generator.safetensors"),
    ] {
        let run = interpolate(&["--from", ms, "--to", to, "--t", t, "--out", out.to_str().unwrap()]);
        assert_eq!(run.status.code(), Some(1), "a runtime error");
        let err = String::from_utf8_lossy(&run.stderr);
        assert!(err.contains(expected), "{expected} not in {err}");
        assert!(!out.exists());
    }
    // Malformed flags are usage errors (2); a well-formed weight that does not fit is found
    // at run time (1).
    for (group, expected, code) in [
        ("trunk", "expected PREFIX=T", 2),
        ("trunk=0.3", "trunk names no parameter of the generator", 1),
        ("template.trunk=-0.1", "the weight of template.trunk is -0.1", 1),
        ("template.trunk=x", "expected a number after '='", 2),
    ] {
        let run =
            interpolate(&["--from", ms, "--to", ms, "--t", "0.4", "--t-for", group, "--out", out.to_str().unwrap()]);
        assert_eq!(run.status.code(), Some(code), "--t-for {group}");
        let err = String::from_utf8_lossy(&run.stderr);
        assert!(err.contains(expected), "{expected} not in {err}");
        assert!(!out.exists());
    }
}
