#!/usr/bin/env bash
# The main job on the embedded default: generate the procedural chairs dataset, then
# render a generator from two viewpoints and time it. Training, inversion and editing
# of real photos join this pipeline as they land (today the generator is randomly
# initialised with the authors' initialisation, so its images are flat).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
scripts/setup.sh
mkdir -p out
cargo build --quiet -p gdrf-train -p gdrf-edit
target/debug/gdrf-train dataset synth --category chairs --count 512 --resolution 64 \
  --out out/chairs64 --contact-sheet --force
target/debug/gdrf-edit render --seeds 0,1 --views 2 --resolution 64 --steps 24 \
  --out out/demo.png --depth-out out/demo_depth.png "$@"
echo "demo: wrote out/chairs64/ (dataset, contact-sheet.png), out/demo.png and out/demo_depth.png"
