//! The shipped blend (models/chairs-tiny-blend) is exactly what its README's command makes
//! from the two generators shipped beside it, and `gdrf-train interpolate` refuses bad input
//! by name.
#[path = "../../gdrf-core/tests/common/mod.rs"]
mod common;

use common::{repo_root, TempDir};
use gdrf_core::checkpoint::load_generator;
use std::process::Command;
use tch::{Device, Kind};

/// The weight of e14 in the shipped blend, as its README states.
const T: &str = "0.4";

fn interpolate(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_gdrf-train"))
        .current_dir(repo_root())
        .arg("interpolate")
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn the_shipped_blend_is_what_its_command_makes() {
    let dir = TempDir::new("shipped-blend").unwrap();
    let out = dir.path("blend.safetensors");
    let run = interpolate(&[
        "--from",
        "models/chairs-tiny-ms/generator.safetensors",
        "--to",
        "models/chairs-tiny-blend/e14.safetensors",
        "--t",
        T,
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let made = load_generator(&out, Device::Cpu, Kind::Float).unwrap();
    let shipped =
        load_generator(&repo_root().join("models/chairs-tiny-blend/generator.safetensors"), Device::Cpu, Kind::Float)
            .unwrap();
    assert_eq!(made.header, shipped.header);
    // Both sources last trained in chairs-tiny's 32² stage (12 + 12 samples), and the blend
    // says so, for the evaluation's resolution warning.
    for (key, want) in [("resolution", "32"), ("samples_per_ray", "24")] {
        for prefix in ["", "from.", "to."] {
            assert_eq!(
                shipped.header.info.get(&format!("{prefix}{key}")).map(String::as_str),
                Some(want),
                "{prefix}{key}"
            );
        }
    }
    let want = shipped.vs.variables();
    let got = made.vs.variables();
    assert_eq!(got.len(), want.len());
    assert_eq!(got.len(), 48);
    for (name, t) in got {
        assert!(t.equal(&want[&name]), "{name} differs from the shipped blend");
    }
}

#[test]
fn interpolate_refuses_bad_input_by_name() {
    let dir = TempDir::new("blend-errors").unwrap();
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
