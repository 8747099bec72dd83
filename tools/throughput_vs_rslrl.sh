#!/usr/bin/env bash
# End-to-end training throughput of host-trainer and of RSL-RL 2.2.4 on the same recipe,
# back to back on this machine, twice (ours, RSL-RL, ours, RSL-RL), ITERATIONS iterations each,
# the referee only after the last (outside the timed part on both sides). Needs the RSL-RL
# Python environment of README "Train from Python". Nothing else should run meanwhile.
#
# - default (issue "learn", item 3): the shipped stage-1 config
#   (host-trainer/configs/stage1.toml), row A; ITERATIONS defaults to 50 (2.56 M samples);
# - --row G (issue [lstm-speed], item 4): recurrent PPO on the race against stage1.blob from
#   a random row-G network, 256 envs x 100 steps, 5 epochs x 4 minibatches, the paper's PPO
#   settings; ours with the fused recurrent update (update = "fused"); ITERATIONS defaults
#   to 10 (256 k samples).
#
#   bash tools/throughput_vs_rslrl.sh [--row G] [OUT_DIR] [ITERATIONS]
set -euo pipefail
cd "$(dirname "$0")/.."
row=A
if [ "${1:-}" = "--row" ]; then
  row=$2
  shift 2
fi
case "$row" in
  A) default_out=runs/throughput; default_iterations=50 ;;
  G) default_out=runs/throughput_G; default_iterations=10 ;;
  *) echo "--row: A or G" >&2; exit 2 ;;
esac
out=${1:-$default_out}
iterations=${2:-$default_iterations}
mkdir -p "$out"
config="$out/row${row}_$iterations.toml"
if [ "$row" = A ]; then
  sed -e "s/^iterations = .*/iterations = $iterations/" \
      -e "s/^eval_every = .*/eval_every = $iterations/" \
      -e "s/^checkpoint_every = .*/checkpoint_every = $iterations/" \
      -e "/^keep_best = /d" -e "/^select = /d" \
      host-trainer/configs/stage1.toml > "$config"
else
  cat > "$config" <<TOML
[run]
name = "throughput-G"
row = "G"
seed = 1
iterations = $iterations
checkpoint_every = $iterations
eval_every = $iterations
eval_races = 1

[env]
num_envs = 256
preset = "paper"
spawn = "stage2"
episode_s = 15.0
random_initial_episode_length = true

[ppo]
steps_per_env = 100
epochs = 5
minibatches = 4
clip = 0.2
gamma = 0.99
lambda = 0.95
value_coef = 1.0
entropy_coef = 0.008
learning_rate = 1e-5
desired_kl = 0.01
max_grad_norm = 1.0
init_std = 1.0
update = "fused"

[reward]
progress = 0.5
command = 0.0005
smoothness = 0.0002
pass = 1.0
crash = 5.0

[race]
opponent = "policies/stage1.blob"
competition = "dense"
competition_weight = 0.5
TOML
fi
cargo build --release -q -p host-trainer -p sitl
trainer=${CARGO_TARGET_DIR:-target}/release/host-trainer
lscpu | grep 'Model name' || true
for round in 1 2; do
  rm -rf "$out/ours_$round" "$out/rslrl_$round"
  "$trainer" train --config "$config" --out "$out/ours_$round" --quiet > "$out/ours_$round.log" 2>&1
  if [ "$row" = A ]; then
    python3 tools/train_rslrl.py --out "$out/rslrl_$round" --row A --iterations "$iterations" \
      --num-envs 512 --steps-per-env 100 --seed 1 --init-std 0.3 --lr 3e-4 --entropy 0.01 \
      --desired-kl 0.01 --spawn along-track --spawn-speed-mps 8 --stage1-fraction 0.2 \
      --stage2-fraction 0.25 --replay-fraction 0.3 --fold-mirror --reward-weight crash=1 \
      --pass-decay 0 1700 2000 --max-std 1.0 --max-std-decay 0.1 800 2000 \
      --init-output-bias 0.519 --velocity-scale-mps 12 --eval-every 0 --eval-episodes 1 \
      --checkpoint-every 0 > "$out/rslrl_$round.log" 2>&1
  else
    python3 tools/train_rslrl.py --out "$out/rslrl_$round" --row G --iterations "$iterations" \
      --num-envs 256 --steps-per-env 100 --seed 1 --opponent policies/stage1.blob \
      --eval-every 0 --eval-episodes 1 --parity-envs 16 --parity-steps 20 \
      --checkpoint-every 0 > "$out/rslrl_$round.log" 2>&1
  fi
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
