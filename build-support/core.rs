//! gdrf-core's build script: the shared libtorch linking (link_libtorch.rs), and the bridge
//! to libtorch's c10d (src/dist/c10d.cpp), compiled against the wheel's headers and the
//! system's gloo headers (Debian's libgloo-dev, which scripts/setup.sh installs). Without
//! the gloo headers the bridge is left out (cfg `gdrf_c10d` unset): the library builds and
//! runs in one process, and joining a process group is an error that says why.
#[path = "link_libtorch.rs"]
#[allow(dead_code)]
mod shared;

use std::path::{Path, PathBuf};

fn main() {
    let lib = shared::libtorch_lib();
    shared::link(&lib);
    bridge(&lib);
}

fn bridge(lib: &Path) {
    println!("cargo::rustc-check-cfg=cfg(gdrf_c10d)");
    println!("cargo:rerun-if-changed=src/dist/c10d.cpp");
    println!("cargo:rerun-if-env-changed=GDRF_GLOO_INCLUDE");
    let gloo = std::env::var_os("GDRF_GLOO_INCLUDE").map_or_else(|| PathBuf::from("/usr/include"), PathBuf::from);
    println!("cargo:rerun-if-changed={}", gloo.join("gloo/algorithm.h").display());
    if !gloo.join("gloo/algorithm.h").exists() {
        println!(
            "cargo:warning=the c10d bridge is not built: no gloo headers in {} (scripts/setup.sh installs \
             libgloo-dev; GDRF_GLOO_INCLUDE names another folder); training runs in one process only",
            gloo.display()
        );
        return;
    }
    let include = lib.parent().expect("torch/lib has a parent").join("include");
    cc::Build::new()
        .cpp(true)
        .std("c++17")
        // ProcessGroupGloo.hpp declares nothing without it.
        .define("USE_C10D_GLOO", None)
        // The PyPI wheels of torch ≥ 2.7 are built with the C++11 ABI.
        .define("_GLIBCXX_USE_CXX11_ABI", "1")
        .include(&include)
        .include(include.join("torch/csrc/api/include"))
        .include(&gloo)
        .warnings(false)
        .file("src/dist/c10d.cpp")
        .compile("gdrf_c10d");
    println!("cargo:rustc-cfg=gdrf_c10d");
}
