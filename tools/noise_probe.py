#!/usr/bin/env python3
"""How a policy blob flies with and without its exploration noise.

PPO trains a Gaussian policy, the referee and the flight controller fly its mean: the
action clip(μ) (eq. 3 maps [-1, 1] to rotor commands). With a large σ the two differ more
than the noise's size suggests, because the mean of the clipped Gaussian, E[clip(μ + σε)],
is not clip(μ): a policy that learned under σ = 1 can push μ past the clip to get the
average action it wants, and flown deterministically it then overshoots.

This probe flies `--envs` copies of the blob from the stage-1 spawn (the referee's) for
`--seconds` of simulated time each, with actions clip(μ + σε) for every σ given, and prints
gates and crashes per second and the success rate (gates passed / (passed + crashes), the
referee's "encountered" counted the same way), and the share of rotor commands the clip holds
at full thrust (+1: a policy flying at the thrust limit has most of them there). σ = 0 is the
deterministic flight the referee scores. Through the `overtake` Python package (sitl/python; `pip install ./sitl/python`).

    python3 tools/noise_probe.py runs/e5/e5.blob --sigma 0 0.3 0.6 1.0
"""

import argparse

import numpy as np

import overtake


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("blob", help="a stage-1 policy blob (row A-D)")
    ap.add_argument("--sigma", type=float, nargs="+", default=[0.0, 0.3, 0.6, 1.0],
                    help="action noise standard deviations to fly (0 = the referee's flight)")
    ap.add_argument("--envs", type=int, default=64, help="copies flown at once (default 64)")
    ap.add_argument("--seconds", type=float, default=45.0,
                    help="simulated seconds per copy (default 45, the referee's episode)")
    ap.add_argument("--preset", default="paper", help="dynamics preset (default paper)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the noise (default 0)")
    a = ap.parse_args()

    policy = overtake.Policy(a.blob)
    print(f"{a.blob}: {a.envs} x {a.seconds:.0f} s from the stage-1 spawn, preset {a.preset}")
    print("| σ | gates/s | crashes/s | success | commands at +1 |\n|---|---|---|---|---|")
    for sigma in a.sigma:
        env = overtake.make_vec_env(
            task="time_trial", num_envs=a.envs, preset=a.preset, seed=a.seed, spawn="stage1",
            episode_s=a.seconds, random_initial_episode_length=False, policy=policy)
        obs, _ = env.reset(seed=a.seed)
        rng = np.random.default_rng(a.seed)
        steps = int(round(a.seconds / env.dt_s))
        gates = crashes = saturated = 0
        for _ in range(steps):
            mean = policy.act(obs)
            noise = sigma * rng.standard_normal(mean.shape)
            action = np.clip(mean + noise, -1.0, 1.0).astype(np.float32)
            saturated += int((action >= 1.0).sum())
            obs, _, _, _, info = env.step(action)
            gates += int(info["gate_passed"].sum())
            crashes += int(info["crashed"].sum())
        sim_s = a.envs * steps * env.dt_s
        print(f"| {sigma:.2f} | {gates / sim_s:.3f} | {crashes / sim_s:.3f} | "
              f"{gates / max(gates + crashes, 1):.3f} | {saturated / (a.envs * steps * 4):.3f} |")


if __name__ == "__main__":
    main()
