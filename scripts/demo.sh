#!/usr/bin/env bash
# The main job on the embedded default. For now: render a randomly initialised
# generator (the release's initialisation) from two viewpoints and time it.
# Later issues extend this to: procedural dataset -> train -> invert -> edit.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
scripts/setup.sh
mkdir -p out
cargo run --quiet -p gdrf-edit -- render --seeds 0,1 --views 2 --resolution 64 --steps 24 \
  --out out/demo.png --depth-out out/demo_depth.png "$@"
echo "demo: wrote out/demo.png and out/demo_depth.png"
