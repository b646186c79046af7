//! gdrf-core's build script: the shared libtorch linking (link_libtorch.rs), and the bridge
//! to libtorch's c10d (src/dist/c10d.cpp), compiled against the wheel's headers and gloo's,
//! which the wheel lacks and third_party/gloo holds (see its README).
#[path = "link_libtorch.rs"]
#[allow(dead_code)]
mod shared;

use std::path::Path;

fn main() {
    let lib = shared::libtorch_lib();
    shared::link(&lib);
    bridge(&lib);
}

fn bridge(lib: &Path) {
    println!("cargo:rerun-if-changed=src/dist/c10d.cpp");
    println!("cargo:rerun-if-changed=third_party/gloo");
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
        .include("third_party/gloo")
        .warnings(false)
        .file("src/dist/c10d.cpp")
        .compile("gdrf_c10d");
}
