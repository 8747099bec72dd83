"""Env-steps per second of other Python drone simulators on this machine's CPU, for the
comparison beside `bench.py` in docs/PERFORMANCE.md ("Through Python"): crazyflow (JAX,
its Gymnasium figure-eight environment) and Genesis (the simulator of the paper's own code,
a scene of crazyflie cf2x drones driven by propeller rpm, as its `examples/drone`).

Both step at the contract's 50 Hz (one env-step = 0.02 s of flight) with random actions
drawn beforehand, 4,096 envs by default, after a warm-up that includes their JIT or kernel
compilation. A benchmark, not a test; neither package is a dependency of `overtake`:

    python3 -m venv .venv-sims && . .venv-sims/bin/activate
    pip install crazyflow torch genesis-world
    python3 sitl/python/bench_others.py [--num-envs 4096] [--seconds 10] [--only crazyflow]
"""

from __future__ import annotations

import argparse
import os
import platform

import numpy as np

from bench import cpu_model, rate

CONTROL_HZ = 50


def crazyflow_rate(n: int, seconds: float) -> tuple[str, float]:
    import crazyflow
    import jax
    from crazyflow.envs.figure_8_env import FigureEightEnv

    env = FigureEightEnv(num_envs=n, freq=CONTROL_HZ, device="cpu")
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    low, high = env.action_space.low, env.action_space.high
    actions = [rng.uniform(low, high).astype(np.float32) for _ in range(16)]

    def step(a):
        obs, *_ = env.step(a)
        jax.block_until_ready(obs)

    for a in actions[:5]:  # JIT compilation
        step(a)
    version = getattr(crazyflow, "__version__", "0.4")
    what = f"crazyflow {version} (JAX {jax.__version__}, CPU), FigureEightEnv"
    return what, rate(step, actions, seconds)[0]


def genesis_rate(n: int, seconds: float) -> tuple[str, float]:
    import genesis as gs
    import torch

    gs.init(backend=gs.cpu, logging_level="warning", seed=0)
    scene = gs.Scene(
        sim_options=gs.options.SimOptions(dt=1.0 / CONTROL_HZ, substeps=2),
        rigid_options=gs.options.RigidOptions(enable_collision=True, enable_joint_limit=True),
        show_viewer=False,
    )
    scene.add_entity(gs.morphs.Plane())
    drone = scene.add_entity(gs.morphs.Drone(file="urdf/drones/cf2x.urdf", pos=(0, 0, 1)))
    scene.build(n_envs=n)
    g = torch.Generator().manual_seed(0)
    # Around the cf2x hover rpm (~14,468), as the paper's env maps its actions.
    rpms = [14468.0 * (1.0 + 0.8 * (torch.rand(n, 4, generator=g) - 0.5)) for _ in range(16)]

    def step(rpm):
        drone.set_propellers_rpm(rpm)
        scene.step()

    for rpm in rpms[:5]:  # kernel compilation
        step(rpm)
    what = f"Genesis {gs.__version__} (CPU backend, torch {torch.__version__})"
    return what, rate(step, rpms, seconds)[0]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--num-envs", type=int, default=4096)
    p.add_argument("--seconds", type=float, default=10.0, help="per measurement")
    p.add_argument("--only", choices=["crazyflow", "genesis"])
    args = p.parse_args()
    print(f"CPU: {cpu_model()} ({os.cpu_count()} logical CPUs), Python {platform.python_version()}")
    for name, fn in (("crazyflow", crazyflow_rate), ("genesis", genesis_rate)):
        if args.only not in (None, name):
            continue
        try:
            what, r = fn(args.num_envs, args.seconds)
        except ImportError as e:
            print(f"{name}: not installed ({e})")
            continue
        print(f"{what}: {args.num_envs} envs, {r / 1e6:.3f} M env-steps/s at {CONTROL_HZ} Hz")


if __name__ == "__main__":
    main()
