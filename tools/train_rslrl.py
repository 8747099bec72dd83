#!/usr/bin/env python3
"""Train a racing policy with RSL-RL (the paper's PPO) on overtake's environments, then take it
to a flash blob and the referee.

    python3 tools/train_rslrl.py --out runs/rslrl_A --row A --iterations 20

What it does, in order:

1. builds ``overtake.rslrl.VecEnv`` (the Rust environments) and RSL-RL's ``OnPolicyRunner``
   with the paper's PPO config for the row (``overtake.rslrl.paper_train_cfg``), optionally
   starting the actor from a blob (``--init-blob``, through ``host-trainer export-rslrl``);
2. trains, writing one JSON line per iteration to ``OUT/metrics.jsonl`` (samples, wall-clock,
   collection and update seconds, gates and crashes per simulated second, reward terms, and,
   every ``--eval-every`` iterations, the referee's success, crash rate and best lap);
3. exports the actor (``OUT/actor.safetensors``, RSL-RL's names), converts it with
   ``host-trainer import-rslrl`` into ``OUT/policy.blob``, and checks the blob against
   PyTorch: the blob's actions (firmware-core, through ``overtake.Policy``) and the actor's
   ``act_inference`` on the same observations, a rollout of the actor itself, resetting
   both at episode ends for an LSTM row. Prints the max abs error and fails above 1e-5;
4. referees the blob (``sitl eval``, 45 s episodes from the stage-1 spawn for a time trial,
   races against the opponent for a race) and prints the result.

A long run spans sessions: every ``--checkpoint-every`` iterations (50) it writes
``OUT/checkpoint.pt`` atomically (networks, σ, Adam, the adaptive learning rate, iteration and
training wall-clock), and the same command with ``--resume`` (and a larger ``--iterations``
if wanted) continues it, its metrics and wall-clock running on from the checkpoint.

Rows: A (time trial, MLP 2x128) and the LSTM rows E, F, G (races against ``--opponent``,
``policies/stage1_guarded.blob`` by default). Needs PyTorch, rsl-rl-lib 2.2.4, tensorboard,
safetensors and the ``overtake`` package (README "Train from Python"); the Rust binaries
are run with ``cargo run --release``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load_file, save_file

import overtake
from overtake.rslrl import VecEnv, actor_state_dict, paper_train_cfg

try:
    from rsl_rl.runners import OnPolicyRunner
except ImportError as e:  # pragma: no cover
    sys.exit(f"error: {e}; pip install rsl-rl-lib==2.2.4 tensorboard")

REPO = Path(__file__).resolve().parent.parent
#: The largest |blob - PyTorch| difference of an action the round trip accepts.
PARITY_TOLERANCE = 1e-5


def cargo(package: str, *args: str) -> str:
    """Runs a workspace binary (built on first use) and returns its stdout."""
    cmd = ["cargo", "run", "--release", "-q", "-p", package, "--", *args]
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    if done.returncode != 0:
        sys.exit(f"error: {' '.join(cmd)} failed:\n{done.stderr.strip()}")
    return done.stdout


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    return parser().parse_args(argv)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="run directory (created)")
    p.add_argument("--row", default="A", choices=["A", "E", "F", "G"], help="Table 1 row")
    p.add_argument("--iterations", type=int, default=20, help="PPO iterations")
    p.add_argument("--num-envs", type=int, default=4096)
    p.add_argument("--steps-per-env", type=int, default=100, help="rollout length")
    p.add_argument("--seed", type=int, default=1, help="torch and environment seed")
    p.add_argument("--threads", type=int, default=2, help="torch threads")
    p.add_argument("--init-blob", type=Path, help="start the actor from this blob's weights")
    p.add_argument("--init-std", type=float, default=1.0, help="initial action noise σ")
    p.add_argument("--lr", type=float, help="initial learning rate (default: the paper's)")
    p.add_argument("--entropy", type=float, help="entropy coefficient (default: the paper's)")
    p.add_argument("--desired-kl", type=float, help="adaptive lr KL target (paper 0.01)")
    p.add_argument("--desired-kl-decay", type=float, nargs=3, metavar=("FINAL", "FROM", "TO"),
                   help="the KL target falls linearly from --desired-kl to FINAL between "
                        "iterations FROM and TO (host-trainer's ppo.desired_kl_decay)")
    p.add_argument("--epochs", type=int, help="epochs per update (paper 5)")
    p.add_argument("--minibatches", type=int, help="minibatches per epoch (paper 4)")
    p.add_argument("--eval-every", type=int, default=0, help="referee every K iterations (0: end only)")
    p.add_argument("--eval-episodes", type=int, default=20)
    p.add_argument("--eval-seed", type=int, default=0)
    p.add_argument("--preset", default="paper")
    p.add_argument("--spawn", default="along-track", choices=["along-track", "stage1"])
    p.add_argument("--episode-s", type=float, default=15.0)
    p.add_argument("--spawn-speed-mps", type=float, default=0.0)
    p.add_argument("--stage1-fraction", type=float, default=0.0)
    p.add_argument("--stage2-fraction", type=float, default=0.0,
                   help="share of the other respawns at the paper's stage-2 start (at rest before a gate)")
    p.add_argument("--replay-fraction", type=float, default=0.0,
                   help="share of respawns from an env's own recent post-pass states")
    p.add_argument("--reward-weight", action="append", default=[], metavar="TERM=W",
                   help="a reward weight other than the paper's, e.g. crash=1 (repeatable)")
    p.add_argument("--pass-decay", type=float, nargs=3, metavar=("FINAL", "FROM", "TO"),
                   help="the pass weight falls linearly to FINAL between iterations FROM and "
                        "TO (host-trainer's [pass_decay]; set between rollouts)")
    p.add_argument("--fold-mirror", action="store_true",
                   help="fold the figure-8 onto one half by its mirror symmetry (host-trainer's "
                        "env.fold_mirror); the blob records the fold")
    p.add_argument("--max-std", type=float,
                   help="σ ceiling: the std parameter is clamped to it after every update "
                        "(host-trainer's ppo.max_std; RSL-RL has none)")
    p.add_argument("--max-std-decay", type=float, nargs=3, metavar=("FINAL", "FROM", "TO"),
                   help="the σ ceiling falls linearly from --max-std to FINAL between "
                        "iterations FROM and TO (host-trainer's ppo.max_std_decay)")
    p.add_argument("--init-output-bias", type=float,
                   help="start the actor's output bias at this action (host-trainer's "
                        "ppo.init_hover: the preset's hover action, 0.519 with paper)")
    p.add_argument(
        "--velocity-scale-mps",
        type=float,
        help="observation velocity scale (default: --init-blob's, else the paper's 3 m/s)",
    )
    p.add_argument("--opponent", type=Path, default=REPO / "policies/stage1_guarded.blob")
    p.add_argument("--parity-envs", type=int, default=256, help="envs of the parity rollout")
    p.add_argument("--parity-steps", type=int, default=200, help="steps of the parity rollout")
    p.add_argument("--checkpoint-every", type=int, default=50,
                   help="write OUT/checkpoint.pt (atomically) every K iterations (0: never)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in OUT from its checkpoint: networks, Adam, the adaptive "
                        "learning rate, σ, the iteration, samples and wall-clock; the metrics "
                        "after the checkpoint are dropped and the environments restart (seeded "
                        "by --seed and the iteration). The arguments that shape training must be "
                        "the run's own (--iterations, --checkpoint-every, --threads and the "
                        "referee's and parity check's may change)")
    return p


#: Arguments a resumed run may change: how long it runs, how often it reports, and where
#: its directory is named from (a relative or moved --out is the same run).
RESUMABLE_CHANGES = {
    "iterations", "checkpoint_every", "resume", "threads", "out",
    "eval_every", "eval_episodes", "eval_seed", "parity_envs", "parity_steps",
}  # fmt: skip


def run_arguments(args: argparse.Namespace) -> dict[str, Any]:
    """The arguments that define a run (those a resume must not change), JSON-comparable."""
    return {
        k: (str(v) if isinstance(v, Path) else v)
        for k, v in sorted(vars(args).items())
        if k not in RESUMABLE_CHANGES
    }


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """``torch.save`` to a temporary file beside ``path``, then an atomic rename: a run
    killed while writing keeps its previous checkpoint."""
    tmp = path.with_suffix(".pt.tmp")
    with tmp.open("wb") as f:
        torch.save(state, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def load_checkpoint(args: argparse.Namespace) -> dict[str, Any]:
    """The run's checkpoint, refused with a clear error when absent or not this run's."""
    path = args.out / "checkpoint.pt"
    if not path.exists():
        sys.exit(f"error: --resume: {path} does not exist (nothing to resume)")
    try:
        state = torch.load(path, weights_only=False)
    except Exception as e:  # a truncated or foreign file
        sys.exit(f"error: --resume: {path} is not a readable checkpoint: {e}")
    if not isinstance(state, dict) or not isinstance(state.get("arguments"), dict):
        sys.exit(f"error: --resume: {path} is not a train_rslrl checkpoint")
    # An argument the checkpoint predates had its default then.
    defaults = parser()
    saved = {k: v for k, v in state["arguments"].items() if k not in RESUMABLE_CHANGES}
    now = run_arguments(args)
    for k in now.keys() - saved.keys():
        d = defaults.get_default(k)
        saved[k] = str(d) if isinstance(d, Path) else d
    changed = sorted(k for k in saved.keys() | now.keys() if saved.get(k) != now.get(k))
    if changed:
        sys.exit(
            "error: --resume with different arguments than the run's own: "
            + ", ".join(f"{k} {saved.get(k)!r} -> {now.get(k)!r}" for k in changed)
        )
    if state["iteration"] > args.iterations:
        sys.exit(
            f"error: --resume: the checkpoint is at iteration {state['iteration']}, past "
            f"--iterations {args.iterations}"
        )
    return state


def keep_metrics_up_to(path: Path, iteration: int) -> None:
    """Drops the metrics lines written after ``iteration`` (a run killed after its last
    checkpoint logged iterations the resumed run trains again)."""
    if not path.exists():
        return
    kept = []
    for line in path.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:  # the torn last line of a killed run
            break
        if row["iteration"] > iteration:
            break
        kept.append(line + "\n")
    tmp = path.with_suffix(".jsonl.tmp")
    tmp.write_text("".join(kept))
    os.replace(tmp, path)


def env_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    race = args.row != "A"
    kw: dict[str, Any] = {
        "task": "race" if race else "time_trial",
        "preset": args.preset,
        "seed": args.seed,
        "episode_s": args.episode_s,
        "row": args.row,
        "velocity_scale_mps": args.velocity_scale_mps,
        # RSL-RL's runner spreads the episode lengths itself (init_at_random_ep_len).
        "random_initial_episode_length": False,
    }
    if race:
        kw["opponent"] = args.opponent
    else:
        kw.update(
            fold_mirror=args.fold_mirror,
            spawn=args.spawn,
            spawn_speed_mps=args.spawn_speed_mps,
            stage1_fraction=args.stage1_fraction,
            stage2_fraction=args.stage2_fraction,
            replay_fraction=args.replay_fraction,
        )
    weights = reward_overrides(args)
    if weights:
        kw["reward_weights"] = weights
    return kw


def reward_overrides(args: argparse.Namespace) -> dict[str, float]:
    """The reward weights ``--reward-weight`` sets (the others are the paper's)."""
    weights = {}
    for item in args.reward_weight:
        term, _, value = item.partition("=")
        try:
            weights[term] = float(value)
        except ValueError:
            sys.exit(f"error: --reward-weight {item}: expected TERM=WEIGHT, e.g. crash=1")
    return weights


def linear_fall(start: float, end: float, first: float, last: float, iteration: int) -> float:
    """``start`` until iteration ``first``, then linearly to ``end`` at ``last`` and after
    (host-trainer's ``linear_fall``: the σ ceiling's and the pass weight's schedules)."""
    t = min(max(iteration - first, 0.0) / max(last - first, 1.0), 1.0)
    return start + (end - start) * t


def rewards_at(args: argparse.Namespace, iteration: int) -> dict[str, float]:
    """The reward weights of the rollout of iteration ``iteration`` (0-based) that differ
    from the paper's: ``--reward-weight``'s, the pass weight lowered by ``--pass-decay``
    (host-trainer's ``TrainConfig::reward_at``)."""
    weights = reward_overrides(args)
    if args.pass_decay is not None:
        final, first, last = args.pass_decay
        weights["pass"] = linear_fall(weights.get("pass", 1.0), final, first, last, iteration)
    return weights


def check_arguments(args: argparse.Namespace) -> None:
    """Refuses, before anything runs, what host-trainer's config validation refuses: a
    schedule without the value it lowers, one that rises, falls to a bad value or backwards
    in time, or iterations that are not whole; and a fold on a race row (the race's
    environment does not fold, so the blob would claim a fold it was not trained with)."""
    if args.fold_mirror and args.row != "A":
        sys.exit(f"error: --fold-mirror folds the time trial (row A), not row {args.row}'s race")
    pass_weight = reward_overrides(args).get("pass", 1.0)
    for flag, decay, start, floor_ok in [
        ("--max-std-decay", args.max_std_decay, args.max_std, False),
        ("--pass-decay", args.pass_decay, pass_weight, True),
        ("--desired-kl-decay", args.desired_kl_decay, args.desired_kl, False),
    ]:
        if decay is None:
            continue
        if start is None:
            sys.exit(f"error: {flag} lowers a value that is not given")
        final, first, last = decay
        low_ok = final >= 0.0 if floor_ok else final > 0.0
        if not (low_ok and final <= start and first < last):
            sys.exit(f"error: {flag} {final:g} {first:g} {last:g}: FINAL must be in "
                     f"{'[0' if floor_ok else '(0'}, {start:g}] and FROM < TO")  # fmt: skip
        if not (first == int(first) >= 0 and last == int(last)):
            sys.exit(f"error: {flag}: FROM and TO are iterations (whole numbers >= 0)")


def max_std_at(args: argparse.Namespace, iteration: int) -> float | None:
    """The σ ceiling of the update after ``iteration`` iterations (host-trainer's
    ``PpoConfig::max_std_at``)."""
    if args.max_std is None:
        return None
    if args.max_std_decay is None:
        return args.max_std
    final, first, last = args.max_std_decay
    return linear_fall(args.max_std, final, first, last, iteration)


def desired_kl_at(args: argparse.Namespace, target: float, iteration: int) -> float:
    """The KL target of the update after ``iteration`` iterations (host-trainer's
    ``PpoConfig::desired_kl_at``): ``target``, lowered by ``--desired-kl-decay``."""
    if args.desired_kl_decay is None:
        return target
    final, first, last = args.desired_kl_decay
    t = linear_fall(0.0, 1.0, first, last, iteration)
    return target if t == 0.0 else target + (final - target) * t


def export_blob(policy: torch.nn.Module, args: argparse.Namespace, name: str) -> Path:
    """The actor as ``OUT/NAME.safetensors`` and ``OUT/NAME.blob``."""
    st = args.out / f"{name}.safetensors"
    save_file(actor_state_dict(policy), str(st))
    blob = args.out / f"{name}.blob"
    cargo(
        "host-trainer", "import-rslrl", "--safetensors", str(st), "--row", args.row,
        "--out", str(blob), "--name", f"rsl-rl {args.row} seed {args.seed}",
        "--velocity-scale-mps", str(args.velocity_scale_mps),
        *(["--fold-mirror"] if args.fold_mirror else []),
    )  # fmt: skip
    return blob


def referee(blob: Path, args: argparse.Namespace) -> dict[str, Any]:
    """``sitl eval`` of the blob: the referee's JSON."""
    out = args.out / "eval.json"
    cmd = ["eval", "--ego", str(blob), "--preset", args.preset, "--episodes",
           str(args.eval_episodes), "--seed", str(args.eval_seed), "--json", str(out)]  # fmt: skip
    if args.row != "A":
        cmd += ["--opponent", str(args.opponent)]
    cargo("sitl", *cmd)
    return json.loads(out.read_text())


def parity(policy: torch.nn.Module, blob: Path, args: argparse.Namespace) -> float:
    """Max |blob − PyTorch| over the actions of a rollout flown by the PyTorch actor's means
    (fresh environments, both policies reset at every episode end)."""
    kw = env_kwargs(args) | {"num_envs": args.parity_envs, "seed": args.seed + 1_000_003}
    env = VecEnv(**kw)
    deployed = overtake.Policy(blob)
    policy.eval()
    recurrent = hasattr(policy, "memory_a")
    if recurrent:
        policy.memory_a.hidden_states = None
        policy.memory_c.hidden_states = None
    obs, _ = env.get_observations()
    worst = 0.0
    with torch.no_grad():
        for _ in range(args.parity_steps):
            mean = policy.act_inference(obs)
            blob_mean = deployed.act(obs.numpy())
            worst = max(worst, float(np.max(np.abs(blob_mean - mean.numpy()))))
            obs, _, dones, _ = env.step(mean)
            if recurrent and bool(dones.any()):
                policy.reset(dones)
                deployed.reset(dones.nonzero().flatten().tolist())
    return worst


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    check_arguments(args)
    # The cargo steps run in the repository: paths given relative to here must not move.
    args.out = args.out.resolve()
    args.opponent = args.opponent.resolve()
    if args.init_blob:
        args.init_blob = args.init_blob.resolve()
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    if args.velocity_scale_mps is None:
        args.velocity_scale_mps = (
            overtake.Policy(args.init_blob).velocity_scale_mps if args.init_blob else 3.0
        )
    resumed = load_checkpoint(args) if args.resume else None
    if not resumed and (args.out / "checkpoint.pt").exists():
        sys.exit(
            f"error: {args.out} holds an earlier run's checkpoint: --resume it, or choose "
            "another --out (a fresh run here would mix its metrics with the earlier run's)"
        )
    start_iteration = resumed["iteration"] if resumed else 0
    args.out.mkdir(parents=True, exist_ok=True)

    # A resumed run's environments restart from a seed of their own (the iteration's), so
    # the rollouts after a resume are not the first ones again.
    env_kw = env_kwargs(args) | {"seed": args.seed + start_iteration}
    env = VecEnv(num_envs=args.num_envs, **env_kw)
    if args.pass_decay is not None:
        env.set_reward_weights(rewards_at(args, start_iteration))
    cfg = paper_train_cfg(args.row)
    cfg["num_steps_per_env"] = args.steps_per_env
    cfg["save_interval"] = max(args.iterations, 1)
    cfg["policy"]["init_noise_std"] = args.init_std
    if args.lr is not None:
        cfg["algorithm"]["learning_rate"] = args.lr
    for key, value in [
        ("entropy_coef", args.entropy),
        ("desired_kl", args.desired_kl),
        ("num_learning_epochs", args.epochs),
        ("num_mini_batches", args.minibatches),
    ]:
        if value is not None:
            cfg["algorithm"][key] = value
    (args.out / "train_cfg.json").write_text(json.dumps(cfg | {"env": env.cfg}, indent=1, default=str))
    runner = OnPolicyRunner(env, cfg, log_dir=str(args.out / "rsl_rl"), device="cpu")
    policy = runner.alg.actor_critic

    if args.init_blob and not resumed:
        st = args.out / "init.safetensors"
        cargo("host-trainer", "export-rslrl", "--blob", str(args.init_blob), "--out", str(st),
              "--std", str(args.init_std))  # fmt: skip
        missing, unexpected = policy.load_state_dict(load_file(str(st)), strict=False)
        if unexpected or any(k.startswith(("actor.", "memory_a.", "std")) for k in missing):
            sys.exit(f"error: {args.init_blob} does not fit row {args.row}: {missing} {unexpected}")

    if args.init_output_bias is not None and not resumed:
        with torch.no_grad():
            policy.actor[-1].bias.fill_(args.init_output_bias)

    metrics_path = args.out / "metrics.jsonl"
    # Wall-clock of training only: the referee's evaluations are timed apart (eval_s).
    now = time.perf_counter()
    clock = {"start": now, "last": now, "iteration": 0, "eval": 0.0}
    if resumed:
        policy.load_state_dict(resumed["model"])
        runner.alg.optimizer.load_state_dict(resumed["optimizer"])
        runner.alg.learning_rate = resumed["learning_rate"]
        torch.set_rng_state(resumed["torch_rng"])
        clock["iteration"] = start_iteration
        runner.current_learning_iteration = start_iteration
        clock["start"] = now - resumed["wall_s"]
        keep_metrics_up_to(metrics_path, start_iteration)
        print(f"resumed {args.out} at iteration {start_iteration} "
              f"({start_iteration * args.num_envs * args.steps_per_env / 1e6:.1f} M samples, "
              f"{resumed['wall_s']:.0f} s of training)")  # fmt: skip
    metrics = metrics_path.open("a" if resumed else "w")
    samples_per_iteration = args.num_envs * args.steps_per_env
    update = runner.alg.update

    def checkpoint(it: int, wall_s: float) -> None:
        save_checkpoint(args.out / "checkpoint.pt", {
            "iteration": it,
            "wall_s": wall_s,
            "model": policy.state_dict(),
            "optimizer": runner.alg.optimizer.state_dict(),
            "learning_rate": runner.alg.learning_rate,
            "desired_kl": runner.alg.desired_kl,
            "torch_rng": torch.get_rng_state(),
            "arguments": run_arguments(args),
        })  # fmt: skip

    kl_target = runner.alg.desired_kl

    def update_and_log() -> tuple:
        t0 = time.perf_counter()
        if args.desired_kl_decay is not None:
            runner.alg.desired_kl = desired_kl_at(args, kl_target, clock["iteration"])
        losses = update()
        ceiling = max_std_at(args, clock["iteration"])
        if ceiling is not None:
            with torch.no_grad():
                policy.std.clamp_(max=ceiling)
        t1 = time.perf_counter()
        clock["iteration"] += 1
        it = clock["iteration"]
        if args.pass_decay is not None:  # the next rollout's weights
            env.set_reward_weights(rewards_at(args, it))
        totals = env.take_totals()
        sim_s = max(totals["steps"], 1) * env.step_dt
        row: dict[str, Any] = {
            "iteration": it,
            "samples": it * samples_per_iteration,
            "wall_s": round(t1 - clock["start"] - clock["eval"], 3),
            "collect_s": round(t0 - clock["last"], 3),
            "update_s": round(t1 - t0, 3),
            "gates_per_s": totals["gates_passed"] / sim_s,
            "crashes_per_s": totals["crashes"] / sim_s,
            "reward_per_step": {k: totals[k] / max(totals["steps"], 1) for k in overtake.REWARD_TERMS},
            "value_loss": losses[0],
            "surrogate_loss": losses[1],
            "entropy": losses[2],
            "learning_rate": runner.alg.learning_rate,
            "std": float(policy.std.detach().mean()),
        }
        if args.pass_decay is not None:  # the weight of the rollout just learned from
            row["pass_weight"] = rewards_at(args, it - 1)["pass"]
        if args.eval_every and it % args.eval_every == 0 and it < args.iterations:
            t2 = time.perf_counter()
            e = referee(export_blob(policy, args, "eval"), args)
            row |= {"eval_success": e["success_rate"], "eval_crash_rate": e["crash_rate"],
                    "eval_best_lap_s": e["best_lap_s"]}  # fmt: skip
            clock["eval"] += time.perf_counter() - t2
        metrics.write(json.dumps(row) + "\n")
        metrics.flush()
        if args.checkpoint_every and it % args.checkpoint_every == 0:
            checkpoint(it, row["wall_s"])
        print(
            f"it {it:4d}  {row['samples'] / 1e6:7.1f} M samples  {row['wall_s']:7.0f} s  "
            f"{samples_per_iteration / (t1 - clock['last']) / 1e3:5.1f} k samples/s  "
            f"gates {row['gates_per_s']:.3f}/s  crashes {row['crashes_per_s']:.3f}/s"
            + (f"  referee success {row['eval_success']:.2f}" if "eval_success" in row else ""),
            flush=True,
        )
        clock["last"] = time.perf_counter()
        return losses

    runner.alg.update = update_and_log
    # A run killed after its last update but before its blob resumes straight to the export.
    if args.iterations > start_iteration:
        runner.learn(args.iterations - start_iteration, init_at_random_ep_len=True)
    wall = clock["last"] - clock["start"] - clock["eval"]
    samples = args.iterations * samples_per_iteration
    # The last update wrote it already when the budget is a multiple of the interval.
    if args.checkpoint_every and args.iterations % args.checkpoint_every:
        checkpoint(args.iterations, wall)
    print(f"trained {args.iterations} iterations, {samples / 1e6:.1f} M samples in {wall:.0f} s "
          f"({samples / wall / 1e3:.1f} k samples/s end to end)")  # fmt: skip

    blob = export_blob(policy, args, "policy")
    err = parity(policy, blob, args)
    print(f"parity: max |blob - PyTorch| = {err:.3g} over {args.parity_envs} envs x "
          f"{args.parity_steps} steps (tolerance {PARITY_TOLERANCE:g})")  # fmt: skip
    e = referee(blob, args)
    lap = "DNF" if e["best_lap_s"] is None else f"{e['best_lap_s']:.2f} s"
    print(f"referee ({e['episodes']} episodes of {e['episode_seconds']:.0f} s, seed {e['seed']}): "
          f"success {e['success_rate']:.3f}, crashes {e['crash_rate']:.3f} /s, best lap {lap}")  # fmt: skip
    (args.out / "summary.json").write_text(json.dumps({
        "iterations": args.iterations, "samples": samples, "wall_s": wall,
        "samples_per_s": samples / wall, "parity_max_abs_err": err, "referee": e,
        "blob": str(blob),
    }, indent=1))  # fmt: skip
    if not err <= PARITY_TOLERANCE:
        print(f"error: the blob differs from PyTorch by {err:.3g} > {PARITY_TOLERANCE:g}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
