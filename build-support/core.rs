//! gdrf-core's build script: the shared libtorch linking (link_libtorch.rs), and the C++
//! bridges compiled against the wheel's headers: the SIREN layers' sine (src/nn/sine.cpp),
//! and libtorch's c10d (src/dist/c10d.cpp), also against gloo's headers, which the wheel
//! lacks and third_party/gloo holds (see its README); with a CUDA libtorch also against the
//! NCCL and CUDA headers of the nvidia wheels, for an NCCL group.
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
    for f in ["src/dist/c10d.cpp", "src/nn/sine.cpp", "src/bridge_error.hpp"] {
        println!("cargo:rerun-if-changed={f}");
    }
    println!("cargo:rerun-if-changed=third_party/gloo");
    let include = lib.parent().expect("torch/lib has a parent").join("include");
    let mut build = cc::Build::new();
    build
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
        .file("src/nn/sine.cpp");
    if let Some(dirs) = nccl_includes(lib) {
        build.define("USE_C10D_NCCL", None).define("USE_CUDA", None).define("GDRF_NCCL", None);
        for d in dirs {
            build.include(d);
        }
    }
    build.compile("gdrf_bridge");
}

/// The header folders of the NCCL group, where the libtorch is a CUDA build: the wheels of
/// NCCL, the CUDA runtime and, for its headers' own includes, CUDA's `crt` and CCCL
/// (scripts/requirements.txt), beside torch in site-packages. None (a bridge with Gloo alone)
/// where any is missing.
fn nccl_includes(lib: &Path) -> Option<Vec<PathBuf>> {
    if !lib.join("libtorch_cuda.so").exists() {
        return None;
    }
    let nvidia = lib.parent()?.parent()?.join("nvidia");
    let cuda = nvidia.join("cu13/include");
    let dirs = vec![nvidia.join("nccl/include"), cuda.clone(), cuda.join("cccl")];
    let wanted = [
        nvidia.join("nccl/include/nccl.h"),
        cuda.join("cuda_runtime_api.h"),
        cuda.join("crt/host_config.h"),
        cuda.join("cccl/nv/target"),
    ];
    for w in &wanted {
        println!("cargo:rerun-if-changed={}", w.display());
    }
    if let Some(missing) = wanted.iter().find(|w| !w.exists()) {
        println!(
            "cargo:warning=the c10d bridge has no NCCL group (CUDA tensors reduce through Gloo): {} is missing; \
             scripts/setup.sh installs it",
            missing.display()
        );
        return None;
    }
    Some(dirs)
}
