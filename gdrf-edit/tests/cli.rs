//! gdrf-edit as a user first meets it: the swap without a subcommand, the shipped model
//! rendered where it learned by default, and exit codes (usage 2, runtime 1) whose
//! messages name the bad flag or file.
#[path = "../../gdrf-core/tests/common/mod.rs"]
mod common;

use common::TempDir;
use std::path::Path;
use std::process::{Command, Output};

fn gdrf_edit(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_gdrf-edit")).args(args).output().expect("gdrf-edit runs")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn size(png: &Path) -> (u32, u32) {
    image::image_dimensions(png).unwrap_or_else(|e| panic!("{}: {e}", png.display()))
}

#[test]
fn the_swap_needs_no_subcommand_and_renders_the_shipped_model_where_it_learned() {
    let dir = TempDir::new("edit-cli-swap").unwrap();
    let (plain, sub) = (dir.path("plain"), dir.path("sub"));
    let swap = ["--shape-from", "seed:0", "--appearance-from", "seed:1", "--views", "2", "--device", "cpu"];
    let o = gdrf_edit(&[&swap[..], &["--out", plain.to_str().unwrap()]].concat());
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    // The shipped model learned at 64² (its checkpoint records it).
    for f in ["frame-000.png", "frame-001.png", "sequence.gif"] {
        assert!(plain.join(f).is_file(), "{f} missing");
    }
    assert_eq!(size(&plain.join("frame-000.png")), (64, 64));
    assert_eq!(size(&plain.join("strip.png")), (128, 64));
    // The same images as the `swap` subcommand with the shipped model named.
    let shipped = common::repo_root().join("models/chairs-campaign/generator.safetensors");
    let o = gdrf_edit(
        &[&["swap"][..], &swap[..], &["--checkpoint", shipped.to_str().unwrap(), "--out", sub.to_str().unwrap()]]
            .concat(),
    );
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    for f in ["frame-000.png", "frame-001.png"] {
        assert_eq!(std::fs::read(plain.join(f)).unwrap(), std::fs::read(sub.join(f)).unwrap(), "{f} differs");
    }
    // --resolution and --samples still choose.
    let big = dir.path("big");
    let o = gdrf_edit(&[&swap[..], &["--resolution", "40", "--samples", "6", "--out", big.to_str().unwrap()]].concat());
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert_eq!(size(&big.join("frame-000.png")), (40, 40));
}

#[test]
fn a_random_generator_comes_only_from_its_flag() {
    let dir = TempDir::new("edit-cli-random").unwrap();
    let out = dir.path("random");
    let o = gdrf_edit(&[
        "--shape-from",
        "seed:0",
        "--appearance-from",
        "seed:1",
        "--random-init",
        "--resolution",
        "16",
        "--samples",
        "4",
        "--device",
        "cpu",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert!(stderr(&o).contains("--random-init: a randomly initialised generator"), "{}", stderr(&o));
    assert_eq!(size(&out.join("frame-000.png")), (16, 16));
    // A checkpoint and --random-init together are a usage error.
    let o = gdrf_edit(&["render", "--random-init", "--checkpoint", "x.safetensors"]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
}

#[test]
fn usage_errors_exit_2_and_runtime_errors_exit_1_naming_what_is_wrong() {
    let dir = TempDir::new("edit-cli-errors").unwrap();
    let out = dir.path("out");
    let out = out.to_str().unwrap();
    // Half a swap.
    let o = gdrf_edit(&["--shape-from", "seed:0"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("--appearance-from"), "{}", stderr(&o));
    // A source of no known kind.
    let o = gdrf_edit(&["--shape-from", "mesh:3", "--appearance-from", "seed:1"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("--shape-from") && stderr(&o).contains("seed:N"), "{}", stderr(&o));
    // A checkpoint that does not exist.
    let o = gdrf_edit(&[
        "--shape-from",
        "seed:0",
        "--appearance-from",
        "seed:1",
        "--checkpoint",
        "no-such-model.safetensors",
        "--out",
        out,
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("no-such-model.safetensors"), "{}", stderr(&o));
    // A resolution out of range, whichever subcommand.
    for sub in [&["--shape-from", "seed:0", "--appearance-from", "seed:1"][..], &["render"][..]] {
        let o = gdrf_edit(&[sub, &["--resolution", "4", "--out", out][..]].concat());
        assert_eq!(o.status.code(), Some(1), "{sub:?}: {}", stderr(&o));
        assert!(stderr(&o).contains("--resolution 4: expected 8 to 4096 pixels"), "{sub:?}: {}", stderr(&o));
    }
}

#[test]
fn render_and_swap_build_an_occupancy_grid_where_it_pays() {
    let dir = TempDir::new("edit-cli-grid").unwrap();
    let out = dir.path("out");
    let png = out.with_extension("png");
    let stdout = |o: &Output| String::from_utf8_lossy(&o.stdout).to_string();
    let at_32 = ["--resolution", "32", "--samples", "12"];
    let render = |extra: &[&str]| {
        let o = gdrf_edit(
            &[&["render", "--seeds", "0", "--device", "cpu", "--out", png.to_str().unwrap()][..], &at_32[..], extra]
                .concat(),
        );
        assert_eq!(o.status.code(), Some(0), "{extra:?}: {}", stderr(&o));
        stdout(&o)
    };
    // At 32² with 12 + 12 samples a ray, four views are 98 304 samples (no grid pays), five
    // 122 880 (a 32³ grid does), forty-four 1.08 M (64³).
    assert!(!render(&["--views", "4"]).contains("occupied cells"));
    assert!(render(&["--views", "5"]).contains("in the occupied cells of a 32³ grid"));
    assert!(render(&["--views", "44"]).contains("in the occupied cells of a 64³ grid"));
    assert!(!render(&["--views", "5", "--grid", "off"]).contains("occupied cells"));
    assert!(render(&["--grid", "16"]).contains("between the first and last occupied cells of a 16³ grid"));
    let swap = ["--shape-from", "seed:0", "--appearance-from", "seed:1", "--device", "cpu", "--force"];
    let o = gdrf_edit(&[&swap[..], &at_32[..], &["--views", "5", "--out", out.to_str().unwrap()]].concat());
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert!(stdout(&o).contains("in the occupied cells of a 32³ grid"), "{}", stdout(&o));
    assert!(out.join("frame-004.png").is_file());
    // Flags that contradict each other, or a size out of range, name the flag.
    let o = gdrf_edit(&["render", "--grid", "off", "--grid-cells", "--out", png.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(stderr(&o).contains("--grid-cells"), "{}", stderr(&o));
    let o = gdrf_edit(&["render", "--grid-threshold=-1", "--out", png.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(stderr(&o).contains("--grid-threshold -1"), "{}", stderr(&o));
    let o = gdrf_edit(&["render", "--grid", "3"]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("grid '3'"), "{}", stderr(&o));
}
