//! The three binaries speak one language: `--device` takes the same values everywhere,
//! `--camera` the same presets, the renderer's noise is seeded by `--noise-seed`, an
//! occupancy grid is `--grid auto|off|N`, every angle is in degrees, and a usage error exits 2 while
//! a runtime error exits 1 naming the bad file.
use std::path::PathBuf;
use std::process::{Command, Output};

/// A binary of the workspace, built beside this test by `cargo test --workspace`.
fn bin(name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("the test's own path");
    let dir = exe.parent().and_then(|d| d.parent()).expect("target/<profile>/deps/..");
    let path = dir.join(format!("{name}{}", std::env::consts::EXE_SUFFIX));
    assert!(path.is_file(), "{} is missing: build the workspace first (cargo test --workspace)", path.display());
    path
}

fn run(name: &str, args: &[&str]) -> Output {
    Command::new(bin(name)).args(args).output().unwrap_or_else(|e| panic!("{name} {args:?}: {e}"))
}

/// Every command line that renders or loads a model, as `(binary, subcommand words)`.
const COMMANDS: &[(&str, &[&str])] = &[
    ("gdrf-train", &[]),
    ("gdrf-train", &["eval"]),
    ("gdrf-invert", &[]),
    ("gdrf-invert", &["train-init"]),
    ("gdrf-invert", &["bench"]),
    ("gdrf-edit", &[]),
    ("gdrf-edit", &["render"]),
    ("gdrf-edit", &["swap"]),
    ("gdrf-edit", &["matrix"]),
    ("gdrf-edit", &["interp"]),
    ("gdrf-edit", &["mesh"]),
    ("gdrf-edit", &["features"]),
    ("gdrf-edit", &["bench"]),
];

/// The help text of flag `flag` (`--device <DEVICE>`): what follows it on its line (short
/// help) and the lines after it up to the next flag (long help).
fn flag_help(help: &str, flag: &str) -> Option<String> {
    let mut lines = help.lines().skip_while(|l| !l.trim_start().starts_with(flag));
    let first = lines.next()?.trim_start()[flag.len()..].trim().to_string();
    let rest = lines.take_while(|l| !l.trim_start().starts_with('-')).map(str::trim).collect::<Vec<_>>();
    Some(format!("{first} {}", rest.join(" ")).trim().to_string())
}

fn help(name: &str, sub: &[&str]) -> String {
    let o = run(name, &[sub, &["--help"][..]].concat());
    assert_eq!(o.status.code(), Some(0), "{name} {sub:?} --help: {}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

#[test]
fn device_camera_and_angles_read_the_same_in_every_binary() {
    for &(name, sub) in COMMANDS {
        let h = help(name, sub);
        let device = flag_help(&h, "--device <DEVICE>").unwrap_or_else(|| panic!("{name} {sub:?}: no --device"));
        assert!(device.trim_start().starts_with("auto, cpu, cuda or cuda:N"), "{name} {sub:?} --device: {device}");
        if let Some(camera) = flag_help(&h, "--camera <CAMERA>") {
            assert!(camera.contains("[possible values: chair, car, carla]"), "{name} {sub:?} --camera: {camera}");
        }
        // The seed of the renderer's noise has one name; `--seed`/`--seeds` are codes or
        // whole runs, never the noise.
        for seed in ["--seed <SEED>", "--seeds <SEEDS>"] {
            if let Some(text) = flag_help(&h, seed) {
                assert!(!text.contains("noise"), "{name} {sub:?} {seed} seeds the noise: {text}");
            }
        }
        // An occupancy grid is asked for in one way: auto, off or a size, with the same
        // threshold and cells-only flags beside it.
        if let Some(text) = flag_help(&h, "--grid <GRID>") {
            assert!(text.contains("`auto`") && text.contains("`off` (or 0)"), "{name} {sub:?} --grid: {text}");
            for beside in ["--grid-cells", "--grid-threshold <GRID_THRESHOLD>"] {
                assert!(flag_help(&h, beside).is_some(), "{name} {sub:?} has --grid but no {beside}");
            }
        }
        for angle in ["--pitch <PITCH>", "--yaw <YAW>", "--pose <PITCH,YAW>", "--photo-pose <PITCH,YAW>"] {
            if let Some(text) = flag_help(&h, angle) {
                assert!(text.contains("degrees"), "{name} {sub:?} {angle}: {text}");
            }
        }
    }
    let with_grid = COMMANDS.iter().filter(|(name, sub)| help(name, sub).contains("--grid <GRID>")).count();
    assert!(with_grid >= 4, "gdrf-invert, gdrf-edit, its render and swap take --grid; {with_grid} commands do");
    for (name, sub) in [("gdrf-invert", &[][..]), ("gdrf-edit", &["swap"][..]), ("gdrf-edit", &["interp"][..])] {
        let h = help(name, sub);
        let noise =
            flag_help(&h, "--noise-seed <NOISE_SEED>").unwrap_or_else(|| panic!("{name} {sub:?}: no --noise-seed"));
        assert!(noise.contains("noise"), "{name} {sub:?} --noise-seed: {noise}");
    }
}

#[test]
fn usage_errors_exit_2_and_runtime_errors_exit_1() {
    for name in ["gdrf-train", "gdrf-invert", "gdrf-edit"] {
        let o = run(name, &["--no-such-flag"]);
        assert_eq!(o.status.code(), Some(2), "{name} --no-such-flag");
    }
    let missing = "no-such-file-anywhere";
    for (name, args) in [
        ("gdrf-train", vec!["--config", "no-such-file-anywhere.toml"]),
        ("gdrf-invert", vec!["no-such-file-anywhere.png"]),
        (
            "gdrf-edit",
            vec![
                "--shape-from",
                "seed:0",
                "--appearance-from",
                "seed:1",
                "--checkpoint",
                "no-such-file-anywhere.safetensors",
            ],
        ),
    ] {
        let o = run(name, &args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{name} {args:?}: {err}");
        assert!(err.contains(missing), "{name} {args:?} does not name the file: {err}");
    }
    // A config that cannot be read leaves no run directory behind (tests run in the
    // package's folder, where its default run directory would be made).
    assert!(!std::path::Path::new("runs").join(missing).exists(), "a run directory was made for a missing config");
}
