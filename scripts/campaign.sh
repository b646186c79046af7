#!/usr/bin/env bash
# The training campaign (docs/training.md, "The campaign"): one long run of
# configs/chairs-campaign.toml in the background, resumed every session.
#
#   scripts/campaign.sh resume   [RUN_DIR]   continue it in the background at low priority, with
#                                            configs/chairs-campaign-cpu.toml (a fresh clone
#                                            first copies models/chairs-campaign/run)
#   scripts/campaign.sh stop     [RUN_DIR]   stop it with a checkpoint (SIGINT), and wait
#   scripts/campaign.sh status   [RUN_DIR]   step, last log line, the curve's last evaluation
#   scripts/campaign.sh snapshot [RUN_DIR]   copy its full state into models/chairs-campaign/run,
#                                            overwriting the previous copy (gdrf-train snapshot;
#                                            stop it first, then commit the copy)
#   scripts/campaign.sh verify   [RUN_DIR] [THREADS]
#                                            resume a scratch copy of the committed state to its
#                                            next logged step and compare that line with the run's
#                                            (on THREADS threads, default the CPU config's: the
#                                            thread count changes the rounding, so it must be the
#                                            one the run had at that step)
#   scripts/campaign.sh ship     [RUN_DIR]   copy the generator its learning curve ranks best
#                                            into models/chairs-campaign (gdrf-train ship); the
#                                            first time it replaces the 32²-trained model, that
#                                            one is kept in models/chairs-campaign-32, with its
#                                            initialiser
#
# RUN_DIR defaults to ../campaign/chairs, outside the checkout. The run records paths
# relative to the repository root, so everything runs from there. The binary runs from a
# copy beside the run directory, so that rebuilding the workspace never touches it.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
cmd="${1:-}"
run="${2:-../campaign/chairs}"
model=models/chairs-campaign
shipped=$model/run
bin="$(dirname "$run")/bin/gdrf-train"
log="$(dirname "$run")/train.log"
cpu_config=configs/chairs-campaign-cpu.toml

die() { printf 'campaign: error: %s\n' "$*" >&2; exit 1; }
running() { pgrep -f -- "gdrf-train --resume $run( |\$)" || true; }

case "$cmd" in
  resume)
    [ -z "$(running)" ] || die "already running in $run (pid $(running))"
    if [ ! -d "$run" ]; then
      [ -d "$shipped/checkpoints" ] || die "$run does not exist and $shipped holds no state to start from"
      mkdir -p "$(dirname "$run")"
      cp -r "$shipped" "$run"
      echo "campaign: copied $shipped to $run"
    fi
    scripts/setup.sh
    cargo build --release --quiet -p gdrf-train
    mkdir -p "$(dirname "$bin")"
    cp target/release/gdrf-train "$bin.tmp" && mv -f "$bin.tmp" "$bin"
    # With this CPU's config, whatever the run's own config is now: a GPU leg leaves the
    # GPU's (batch 32) behind, and older states name bfloat16, which a CPU without bfloat16
    # instructions computes many times slower than float32 ("auto" picks).
    nohup nice -n 19 "$bin" --resume "$run" --config "$cpu_config" --quiet >>"$log" 2>&1 &
    echo "campaign: resumed $run in the background (pid $!), log $log"
    ;;
  stop)
    pid="$(running)"
    [ -n "$pid" ] || die "not running in $run"
    kill -INT $pid
    while kill -0 $pid 2>/dev/null; do sleep 1; done
    tail -n 3 "$log"
    ;;
  status)
    [ -d "$run" ] || die "$run does not exist"
    pid="$(running)"
    state="stopped"
    [ -z "$pid" ] || state="running (pid $pid)"
    echo "campaign: $state; newest checkpoint $(ls "$run/checkpoints" | tail -n 1)"
    [ -f "$log" ] && grep '^step' "$log" | tail -n 1
    if [ -f "$run/curve.jsonl" ]; then
      tail -n 1 "$run/curve.jsonl" | "${GDRF_PYTHON:-python3}" -c '
import json, sys
l = json.loads(sys.stdin.read())
pos = {s["score"]: s["mean"]["position"] for s in l["scores"]["scores"]}
print("last evaluation: step", l["step"], "images", l["images_seen"], "positions",
      {k: (round(v, 3) if v is not None else None) for k, v in pos.items()})'
    fi
    ;;
  snapshot)
    [ -z "$(running)" ] || die "still running in $run (pid $(running)); stop it first (scripts/campaign.sh stop)"
    cargo build --release --quiet -p gdrf-train
    target/release/gdrf-train snapshot "$run" --out "$shipped"
    echo "campaign: commit it (git add -A $shipped)"
    ;;
  verify)
    # Whether the committed copy continues the run: a scratch copy of it, resumed with the
    # campaign's binary and the CPU's config to its next logged step, must write the line the
    # run wrote at that step, in every key but the two timings.
    [ -d "$shipped/checkpoints" ] || die "$shipped holds no state"
    [ -x "$bin" ] || die "no $bin; scripts/campaign.sh resume builds it"
    newest="$(ls "$shipped/checkpoints" | tail -n 1)"
    from="$(echo "$newest" | sed 's/^step-0*//; s/\.safetensors$//')"
    every="$(sed -n 's/^log_interval *= *//p' "$cpu_config")"
    to=$(( (from + every - 1) / every * every ))
    grep -q "\"step\":$to," "$run/metrics.jsonl" || die "$run has not logged step $to yet"
    scratch="$(mktemp -d)"
    trap 'rm -rf "$scratch"' EXIT
    cp -r "$shipped" "$scratch/run"
    threads=()
    [ -z "${3:-}" ] || threads=(--threads "$3")
    nice -n 19 "$bin" --resume "$scratch/run" --config "$cpu_config" --steps $(( to - from + 1 )) "${threads[@]}" --quiet >/dev/null
    "${GDRF_PYTHON:-python3}" - "$run/metrics.jsonl" "$scratch/run/metrics.jsonl" "$to" <<'PY'
import json, sys
def logged(path, step):
    lines = [json.loads(l) for l in open(path)]
    found = [l for l in lines if l.get("step") == step and "event" not in l]
    if not found:
        sys.exit(f"campaign: error: {path} has no line for step {step}")
    line = found[-1]
    for timing in ("step_seconds", "images_per_second"):
        line.pop(timing, None)
    return line
run, copy = logged(sys.argv[1], int(sys.argv[3])), logged(sys.argv[2], int(sys.argv[3]))
differ = sorted(k for k in run.keys() | copy.keys() if run.get(k) != copy.get(k))
if differ:
    sys.exit(f"campaign: error: step {sys.argv[3]}: the copy's line differs from the run's in {differ}")
print(f"campaign: resumed from the committed copy, step {sys.argv[3]}'s line equals the run's ({len(run)} keys, timings aside)")
PY
    ;;
  ship)
    cargo build --release --quiet -p gdrf-train
    # The model trained at 32² (step 95 000) is kept in models/chairs-campaign-32 when a
    # generator of the 64² stage first replaces it: scripts/figures.sh draws the two side by side.
    before="$(mktemp)"
    trap 'rm -f "$before"' EXIT
    cp "$model/generator.safetensors" "$before"
    target/release/gdrf-train ship "$run" --out "$model"
    if [ ! -f "$model-32/generator.safetensors" ] && ! cmp -s "$before" "$model/generator.safetensors"; then
      mkdir -p "$model-32"
      cp "$before" "$model-32/generator.safetensors.tmp" && mv -f "$model-32/generator.safetensors.tmp" "$model-32/generator.safetensors"
      echo "campaign: kept the generator it replaced in $model-32"
      # Its initialiser belongs to it (gdrf-invert refuses it for any other generator):
      # it moves with it, and the new one is trained by the command in docs/inversion.md.
      for f in "$model"/initialiser*; do
        [ -e "$f" ] || continue
        mv -f "$f" "$model-32/"
        echo "campaign: moved $(basename "$f") with it"
      done
    fi
    ;;
  *)
    sed -n '2,27p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'
    [ -z "$cmd" ] || exit 2
    ;;
esac
