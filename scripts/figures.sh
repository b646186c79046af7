#!/usr/bin/env bash
# Re-makes the README's figures of the shipped model (models/chairs-campaign) after
# `scripts/campaign.sh ship`, with the main command's settings (scripts/demo.sh):
#   models/chairs-campaign/turntable-64.png     seeds 0–5 in rows, 4 views (64², 12 + 12 samples)
#   models/chairs-campaign/swap-matrix-64.png   shape of seed i in row i, appearance of seed j in column j
#   docs/images/turntable-128-chairs-campaign.png  the same seeds and views at 128², 24 + 24 samples
#   docs/images/orbit-chairs-campaign.gif       seed 0's shape with seed 2's appearance, 24 views
#   docs/images/eval-chairs-campaign.png        the seed-0 evaluation report at 64² (500 images,
#                                               a 16 × 16 swap matrix: the curve's settings)
#   docs/images/invert-chairs-campaign.png      a held-out photo inverted: photo, reconstruction,
#                                               four novel views, its appearance on seed 0's shape
#   docs/images/invert-orbit-chairs-campaign.gif  the inverted features' 12-view orbit (where the
#                                               model learned)
#   docs/images/serve.png                       gdrf-edit serve's page in headless Chromium, after
#                                               its browser test (turned, swapped, a photo inverted)
#   docs/images/side-by-side-64.png             where models/chairs-campaign-32 holds the model
#                                               trained at 32² (kept by `campaign.sh ship`): its
#                                               turntable beside the shipped model's, same seeds, 64²
# Intermediate outputs go to out/figures/. Release binaries: 2 min 21 s on two cores.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
scripts/setup.sh
cargo build --release --quiet -p gdrf-train -p gdrf-edit -p gdrf-invert
train=target/release/gdrf-train
edit=target/release/gdrf-edit
invert=target/release/gdrf-invert
model=models/chairs-campaign/generator.safetensors
dir=models/chairs-campaign
tmp=out/figures
mkdir -p "$tmp" docs/images
# Copies through a temporary name, so an interrupted run never leaves half a figure.
place() { cp "$1" "$2.tmp" && mv -f "$2.tmp" "$2"; }
[ -d data/chairs-64 ] || "$train" dataset prepare --config configs/chairs-tiny.toml

"$edit" render --checkpoint "$model" --seeds 0,1,2,3,4,5 --views 4 --resolution 64 --samples 12 \
  --no-jitter --out "$dir/turntable-64.png"
"$edit" matrix --checkpoint "$model" --sources seed:0,seed:1,seed:2,seed:3 --resolution 64 --samples 12 \
  --yaw 30 --out "$dir/swap-matrix-64.png"
# Above where it learned: 128², twice the samples per ray.
"$edit" render --checkpoint "$model" --seeds 0,1,2,3,4,5 --views 4 --resolution 128 --samples 24 \
  --no-jitter --out docs/images/turntable-128-chairs-campaign.png
"$edit" swap --checkpoint "$model" --shape-from seed:0 --appearance-from seed:2 --orbit 24 --resolution 64 \
  --samples 12 --out "$tmp/orbit" --force
place "$tmp/orbit/sequence.gif" docs/images/orbit-chairs-campaign.gif
"$train" eval --generator "$model" --dataset data/chairs-64 --probe models/chairs-probe/probe.safetensors \
  --num 500 --resolution 64 --swap 16 --samples 12 --out "$tmp/eval"
place "$tmp/eval/report.png" docs/images/eval-chairs-campaign.png
if [ -f models/chairs-campaign-32/generator.safetensors ]; then
  "$edit" render --checkpoint models/chairs-campaign-32/generator.safetensors --seeds 0,1,2,3,4,5 --views 4 \
    --resolution 64 --samples 12 --no-jitter --out "$tmp/turntable-32.png"
  "${GDRF_PYTHON:-.venv/bin/python}" scripts/side_by_side.py "$tmp/turntable-32.png" "$dir/turntable-64.png" \
    docs/images/side-by-side-64.png "trained at 32 px (step 95 000)" "trained at 64 px (shipped)"
fi
# A held-out chair of the dataset (never trained on), its pose estimated (the defaults).
"$invert" data/chairs-64/images/000020.png --generator "$model" --orbit 12 \
  --out "$tmp/invert" --force --quiet
"$edit" swap --checkpoint "$model" --shape-from seed:0 --appearance-from "$tmp/invert/features.safetensors" \
  --orbit 12 --resolution 64 --samples 12 --out "$tmp/invert-swap" --force
place "$tmp/invert/orbit.gif" docs/images/invert-orbit-chairs-campaign.gif
# The strip: photo, reconstruction, orbit views 2, 4, 6, 8 (yaw +60° to +240° from the
# photo's), the swap's first frame; each enlarged to 128² without smoothing.
"${GDRF_PYTHON:-.venv/bin/python}" - "$tmp" docs/images/invert-chairs-campaign.png <<'EOF'
import os, sys
from PIL import Image
tmp, out = sys.argv[1], sys.argv[2]
paths = [f"{tmp}/invert/input.png", f"{tmp}/invert/reconstruction.png"]
paths += [f"{tmp}/invert/orbit/frame-{k:03d}.png" for k in (2, 4, 6, 8)]
paths += [f"{tmp}/invert-swap/frame-000.png"]
tiles = [Image.open(p).convert("RGB").resize((128, 128), Image.NEAREST) for p in paths]
strip = Image.new("RGB", (128 * len(tiles), 128), "white")
for k, t in enumerate(tiles):
    strip.paste(t, (128 * k, 0))
strip.save(out + ".tmp.png")
os.replace(out + ".tmp.png", out)
EOF
# The viewer's page as its browser test leaves it (needs chromium and chromedriver).
GDRF_SCREENSHOT="$root/$tmp/serve.png" cargo test --quiet -p gdrf-edit --test browser the_page_turns >/dev/null
place "$tmp/serve.png" docs/images/serve.png
echo "figures: $dir/turntable-64.png, $dir/swap-matrix-64.png, docs/images/turntable-128-chairs-campaign.png,"
echo "         docs/images/{orbit,eval,invert,invert-orbit}-chairs-campaign.*, docs/images/serve.png"
echo "         the inversion's PSNR and time: $tmp/invert/invert.json"
