#!/usr/bin/env bash
# Issue "learn", item 3: end-to-end training throughput of host-trainer and of RSL-RL 2.2.4 on
# the shipped config (host-trainer/configs/stage1.toml), back to back on this machine, twice
# (ours, RSL-RL, ours, RSL-RL): ITERATIONS iterations each (default 50 = 2.56 M samples), the
# referee only after the last (outside the timed part on both sides; no selection, which
# only starts at iteration 2,000). Needs the RSL-RL Python
# environment of README "Train from Python". Nothing else should run meanwhile.
#
#   bash tools/throughput_vs_rslrl.sh [OUT_DIR] [ITERATIONS]
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-runs/throughput}
iterations=${2:-50}
mkdir -p "$out"
config="$out/stage1_$iterations.toml"
sed -e "s/^iterations = .*/iterations = $iterations/" \
    -e "s/^eval_every = .*/eval_every = $iterations/" \
    -e "s/^checkpoint_every = .*/checkpoint_every = $iterations/" \
    -e "/^keep_best = /d" -e "/^select = /d" \
    host-trainer/configs/stage1.toml > "$config"
cargo build --release -q -p host-trainer -p sitl
trainer=${CARGO_TARGET_DIR:-target}/release/host-trainer
lscpu | grep 'Model name' || true
for round in 1 2; do
  rm -rf "$out/ours_$round" "$out/rslrl_$round"
  "$trainer" train --config "$config" --out "$out/ours_$round" --quiet > "$out/ours_$round.log" 2>&1
  python3 tools/train_rslrl.py --out "$out/rslrl_$round" --row A --iterations "$iterations" \
    --num-envs 512 --steps-per-env 100 --seed 1 --init-std 0.3 --lr 3e-4 --entropy 0.01 \
    --desired-kl 0.01 --spawn along-track --spawn-speed-mps 8 --stage1-fraction 0.2 \
    --stage2-fraction 0.25 --replay-fraction 0.3 --fold-mirror --reward-weight crash=1 \
    --pass-decay 0 1700 2000 --max-std 1.0 --max-std-decay 0.1 800 2000 \
    --init-output-bias 0.519 --velocity-scale-mps 12 --eval-every 0 --eval-episodes 1 \
    --checkpoint-every 0 > "$out/rslrl_$round.log" 2>&1
done
python3 - "$out" <<'PY'
import json, statistics as st, sys
out = sys.argv[1]
for r in (1, 2):
    o = [json.loads(l) for l in open(f"{out}/ours_{r}/metrics.jsonl")]
    p = [json.loads(l) for l in open(f"{out}/rslrl_{r}/metrics.jsonl")]
    so, sp = o[-1]["samples"] / o[-1]["wall_s"], p[-1]["samples"] / p[-1]["wall_s"]
    print(f"round {r}: ours {so / 1e3:.1f} k samples/s (rollout {st.median(x['rollout_s'] for x in o):.3f} s, "
          f"update {st.median(x['update_s'] for x in o):.3f} s per iteration); RSL-RL {sp / 1e3:.1f} k samples/s "
          f"(collect {st.median(x['collect_s'] for x in p):.3f} s, update {st.median(x['update_s'] for x in p):.3f} s); "
          f"ratio {so / sp:.2f}")
PY
