//! Shared build script of every gdrf crate: gives binaries and test executables an
//! rpath to the libtorch of the project's Python environment (so nothing needs
//! LD_LIBRARY_PATH) and keeps libtorch_cuda linked even though no symbol of it is
//! referenced directly, so that CUDA is found at run time where a GPU exists.
use std::path::PathBuf;

fn main() {
    link(&libtorch_lib());
}

/// The folder of the project's libtorch (`libtorch_cpu.so` and friends).
pub fn libtorch_lib() -> PathBuf {
    println!("cargo:rerun-if-env-changed=GDRF_LIBTORCH_LIB");
    println!("cargo:rerun-if-env-changed=LIBTORCH");
    let lib = std::env::var_os("GDRF_LIBTORCH_LIB")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("LIBTORCH").map(|p| PathBuf::from(p).join("lib")));
    let Some(lib) = lib else {
        panic!("libtorch location unknown: run scripts/setup.sh first (it writes .cargo/config.toml), or set LIBTORCH");
    };
    if !lib.join("libtorch_cpu.so").exists() {
        panic!("{} holds no libtorch_cpu.so: re-run scripts/setup.sh", lib.display());
    }
    lib
}

/// The rpath to `lib`, and libtorch_cuda kept linked where it exists.
pub fn link(lib: &std::path::Path) {
    println!("cargo:rustc-link-arg=-Wl,-rpath,{}", lib.display());
    if lib.join("libtorch_cuda.so").exists() {
        println!("cargo:rustc-link-arg=-Wl,-L{}", lib.display());
        println!("cargo:rustc-link-arg=-Wl,--no-as-needed,-ltorch_cuda,--as-needed");
    }
}
