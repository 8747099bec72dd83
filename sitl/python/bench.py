"""Env-steps per second through Python: 4,096 envs stepped with random actions, a time trial
and a race (against policies/stage1.blob, the shipped opponent), through the Gymnasium `step` (with its
infos) and through the bare Rust step (no infos). A benchmark, not a test: it prints rates.

    python3 sitl/python/bench.py [--num-envs 4096] [--seconds 5]
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np

OPPONENT = Path(__file__).resolve().parents[2] / "policies" / "stage1.blob"


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def rate(step, actions, seconds: float, per_call: int = 1) -> tuple[float, int]:
    """Env-steps/s of `step` cycling through `actions` for about `seconds` (after a warm-up);
    each call takes `per_call` steps of `actions[i].shape[-2]` envs."""
    step(actions[0])
    steps, start = 0, time.perf_counter()
    while True:
        for a in actions:
            step(a)
        steps += len(actions) * per_call
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            return steps * actions[0].shape[-2] / elapsed, steps


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--num-envs", type=int, default=4096)
    p.add_argument("--seconds", type=float, default=5.0, help="per measurement")
    args = p.parse_args()
    import overtake  # here, so that bench_others.py can share cpu_model without it

    n = args.num_envs
    print(f"CPU: {cpu_model()} ({os.cpu_count()} logical CPUs), Python {platform.python_version()}")
    rng = np.random.default_rng(0)
    # Random actions, drawn beforehand so that the rate is the environment's, not numpy's.
    actions = [rng.uniform(-1, 1, (n, 4)).astype(np.float32) for _ in range(32)]
    for task in ("time_trial", "race"):
        env = overtake.make_vec_env(
            task=task,
            num_envs=n,
            opponent=OPPONENT if task == "race" else None,
            random_initial_episode_length=True,
            # The plain figure-8, as every rate in docs/PERFORMANCE.md was measured on.
            fold_mirror=False,
        )
        env.reset(seed=0)
        # The same steps inside one Rust loop (no Python in between): the binding's cost is
        # the distance to it, whatever else the machine is doing.
        stacked = np.stack(actions)
        rollout = [stacked]
        runs = (
            ("gymnasium step", env.step, actions),
            ("bare step", env._env.step, actions),
            ("Rust loop", lambda a: env.rollout(a), rollout),
        )
        for name, step, acts in runs:
            r, steps = rate(step, acts, args.seconds, per_call=len(acts[0]) if name == "Rust loop" else 1)
            print(f"{task:10} {name:15} {n} envs: {r / 1e6:6.2f} M env-steps/s ({steps} steps)")


if __name__ == "__main__":
    main()
