#!/usr/bin/env bash
# The main job on the embedded default:
#   1. the procedural chairs dataset (generated on first use by the training config),
#   2. a short training run of configs/chairs-tiny.toml (a few minutes: the loop, its
#      checkpoints, metrics, preview grids and loss curves in out/demo-run/; continue it
#      with `target/debug/gdrf-train --resume out/demo-run`),
#   3. samples on a turntable and a shape/appearance swap matrix from the model shipped
#      in models/chairs-tiny/ (trained with the same config for hours),
#   4. its evaluation (Fréchet/kernel distances, topology coverage, disentanglement, pose
#      consistency beside the real-data and random-generator ends) with the shipped probe.
# DEMO_MINUTES sets the length of step 2 (default 3).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
scripts/setup.sh
mkdir -p out
cargo build --quiet -p gdrf-train -p gdrf-edit
train=target/debug/gdrf-train
edit=target/debug/gdrf-edit

"$train" --config configs/chairs-tiny.toml --run-dir out/demo-run --force --minutes "${DEMO_MINUTES:-3}"
"$train" plot out/demo-run

model=models/chairs-tiny/generator.safetensors
# Rows: seeds 0–5; columns: 4 views around the object.
"$edit" render --checkpoint "$model" --seeds 0,1,2,3,4,5 --views 4 --resolution 64 --steps 12 \
  --no-jitter --out out/samples.png
# Row i keeps the shape of seed i, column j takes the appearance of seed j.
shapes=() apps=()
for i in 0 1 2 3; do for j in 0 1 2 3; do shapes+=("$i"); apps+=("$j"); done; done
"$edit" render --checkpoint "$model" --seeds "$(IFS=,; echo "${shapes[*]}")" \
  --appearance-seeds "$(IFS=,; echo "${apps[*]}")" --cols 4 --resolution 64 --steps 12 \
  --no-jitter --yaw 30 --out out/swap.png
# 200 images keep this to a few minutes; the figures in the README use --num 1000.
"$train" eval --generator "$model" --dataset data/chairs-64 --probe models/chairs-probe/probe.safetensors \
  --num 200 --out out/eval
echo "demo: out/demo-run/ (training run: samples/, metrics.jsonl, losses.png), out/samples.png, out/swap.png and out/eval/ (shipped model)"
