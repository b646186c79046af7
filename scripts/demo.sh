#!/usr/bin/env bash
# The main job on the embedded default:
#   1. the procedural chairs dataset (generated on first use by the training config),
#   2. a short training run of configs/chairs-tiny.toml (a few minutes: the loop, its
#      checkpoints, metrics, preview grids and loss curves in out/demo-run/; continue it
#      with `target/debug/gdrf-train --resume out/demo-run`),
#   3. samples on a turntable and a shape/appearance swap matrix from the model shipped
#      in models/chairs-campaign/ (the training campaign's checkpoint its learning curve
#      ranks best, days on 2-core CPUs; trained at 64² since its step 205 046),
#   4. editing with it: a swap matrix with kept shape sides, an orbit GIF of one shape with
#      another's appearance, an appearance interpolation and a mesh with correspondence
#      colours,
#   5. a held-out photo of the dataset inverted into features (reconstruction, novel-view
#      orbit, loss curve), and its appearance on another shape,
#   6. its evaluation (Fréchet/kernel distances, topology coverage, disentanglement, pose
#      consistency beside the real-data and random-generator ends) with the shipped probe.
# DEMO_MINUTES sets the length of step 2 (default 3).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
scripts/setup.sh
mkdir -p out
cargo build --quiet -p gdrf-train -p gdrf-edit -p gdrf-invert
train=target/debug/gdrf-train
edit=target/debug/gdrf-edit
invert=target/debug/gdrf-invert

"$train" --config configs/chairs-tiny.toml --run-dir out/demo-run --force --minutes "${DEMO_MINUTES:-3}"
"$train" plot out/demo-run

model=models/chairs-campaign/generator.safetensors
# Rows: seeds 0–5; columns: 4 views around the object.
"$edit" render --checkpoint "$model" --seeds 0,1,2,3,4,5 --views 4 --resolution 64 --samples 12 \
  --no-jitter --out out/samples.png
# Row i keeps the shape of seed i, column j takes the appearance of seed j (each row's shape
# side is computed once and re-shaded).
"$edit" matrix --checkpoint "$model" --sources seed:0,seed:1,seed:2,seed:3 --resolution 64 --samples 12 \
  --yaw 30 --out out/swap.png
# The shape of seed 0 with the appearance of seed 2 on a 24-view orbit (frames, strip, GIF).
"$edit" swap --checkpoint "$model" --shape-from seed:0 --appearance-from seed:2 --orbit 24 --resolution 64 \
  --samples 12 --out out/orbit --force
# Seed 0's shape while its appearance moves to seed 3's.
"$edit" interp --checkpoint "$model" --from seed:0 --to seed:3 --what appearance --frames 8 --resolution 64 \
  --samples 12 --out out/interp --force
# A mesh of seed 1 coloured by template-space position (correspondences across shapes).
"$edit" mesh --checkpoint "$model" --source seed:1 --resolution 96 --colour template --out out/chair1.ply
# A held-out chair of the dataset (never trained on), inverted as `gdrf-invert photo.png` does
# (the shipped initialiser's w_s and pose estimate, then the default steps) into
# out/invert/features.safetensors, then its appearance on seed 0's shape.
"$invert" data/chairs-64/images/000020.png --generator "$model" --orbit 12 \
  --out out/invert --force --quiet
"$edit" swap --checkpoint "$model" --shape-from seed:0 --appearance-from out/invert/features.safetensors \
  --orbit 12 --resolution 64 --samples 12 --out out/invert-swap --force
# Scored where it learned (64², 12 + 12 samples). 200 images keep this to a few minutes;
# the figures in the README use --num 500 and a 16 × 16 swap matrix.
"$train" eval --generator "$model" --dataset data/chairs-64 --probe models/chairs-probe/probe.safetensors \
  --num 200 --resolution 64 --samples 12 --out out/eval
echo "demo: out/demo-run/ (training run: samples/, metrics.jsonl, losses.png); from the shipped model:"
echo "      out/samples.png, out/swap.png, out/orbit/, out/interp/, out/chair1.ply, out/invert/,"
echo "      out/invert-swap/ and out/eval/"
