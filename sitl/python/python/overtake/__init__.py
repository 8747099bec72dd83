"""Overtake's drone-racing simulator as Gymnasium vector environments, and its flash-blob policies.

The environments are ``sitl::env::VecEnv`` (Rust, stepped in parallel with the GIL
released); rewards, episode ends and observations are the Rust environment's, unchanged
(docs/DESIGN.md "Rewards", "Observations"). Two entry points:

- :func:`make_vec_env` builds a :class:`OvertakeVecEnv` (a ``gymnasium.vector.VectorEnv``);
- :class:`Policy` computes a flash blob's actions (its Gaussian means) for batches of
  observations, through firmware-core, the code the flight controller runs.
"""

from __future__ import annotations

import os
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv

from overtake._overtake import ACTION_DIM, Policy, RustVecEnv

__all__ = ["ACTION_DIM", "OvertakeVecEnv", "Policy", "make_vec_env"]

#: The reward's terms, as ``infos`` carries them (each × dt, signed as it enters the reward).
REWARD_TERMS = ("progress", "command", "smoothness", "pass", "crash", "competition")
#: The events of a step, as ``infos`` carries them.
EVENTS = ("gate_passed", "crashed", "timed_out", "opponent_crashed")


def make_vec_env(
    task: str = "time_trial",
    num_envs: int = 1024,
    preset: str = "paper",
    seed: int = 0,
    spawn: str = "along-track",
    opponent: str | os.PathLike[str] | None = None,
    episode_s: float = 15.0,
    *,
    random_initial_episode_length: bool = False,
    competition: str = "dense",
    competition_weight: float = 0.5,
    row: str | None = None,
    velocity_scale_mps: float = 3.0,
    spawn_speed_mps: float = 0.0,
    stage1_fraction: float = 0.0,
    stage2_fraction: float = 0.0,
    replay_fraction: float = 0.0,
    racing_line_fraction: float = 0.0,
    reward_weights: dict[str, float] | None = None,
    fold_mirror: bool = False,
) -> OvertakeVecEnv:
    """``num_envs`` auto-resetting environments of a time trial or a race.

    Args:
        task: ``"time_trial"`` (stage 1, one drone) or ``"race"`` (stage 2: against
            ``opponent``, spawned as the paper's stage 2 whatever ``spawn`` says).
        num_envs: number of parallel environments.
        preset: dynamics preset, ``"paper"``, ``"nominal"`` or ``"realistic"``.
        seed: seed of the spawns (env i draws from stream i); ``reset(seed=s)`` rebuilds
            the environments as if made with ``seed=s``.
        spawn: time-trial spawns, ``"along-track"`` (a uniform point of the centreline) or
            ``"stage1"`` (the paper's fixed start).
        opponent: race only: path of the opponent's flash blob (a time-trial, row-A policy).
        episode_s: episode length (s) before a time-out.
        random_initial_episode_length: start each env at a random point of its first
            episode (RSL-RL's ``init_at_random_ep_len``), so that time-outs spread out.
        competition: race only: ``"dense"`` (paper eq. 6), ``"sparse"`` (eq. 7) or
            ``"lead"``.
        competition_weight: race only: its weight λ_c (paper 0.5).
        row: Table 1 row whose observation layout to use (``"A"``: 17 values, the default of
            a time trial; ``"B"``: 20; ``"C"``-``"G"``: 30, ``"G"`` the default of a race).
        velocity_scale_mps: the own-velocity scale of the observation (paper 3 m/s; the
            shipped policies' is ``Policy(path).velocity_scale_mps``).
        spawn_speed_mps: time trial: highest initial speed along the spawn's heading.
        stage1_fraction: time trial: share of respawns at the paper's fixed start.
        stage2_fraction: time trial: share of the respawns neither replayed nor at the
            fixed start at the paper's stage-2 start (at rest, 2 m or 1 m before a random
            gate), where a stage-1 policy starts as stage 2's opponent.
        replay_fraction: time trial: share of respawns from the state right after one of
            the env's own recent gate passes (when it has one; Song et al. 2023).
        racing_line_fraction: time trial: share of the other respawns (neither replayed nor
            at the fixed start nor stage-2) on the ``paper`` preset's time-optimal lap, moving as the
            optimum does there (``tools/min_lap_time.py``; only its states are used).
        reward_weights: the reward's weights that differ from the paper's, by term name
            (``progress`` 0.5, ``command`` 0.0005, ``smoothness`` 0.0002, ``pass`` 1,
            ``crash`` 5; e.g. ``{"crash": 1.0}``, as ``[reward]`` in host-trainer's configs).
        fold_mirror: observe the figure-8 folded onto one half by its mirror symmetry
            (host-trainer's ``env.fold_mirror``): a step flying to the mirrored half's gates
            observes its mirror image, and its action is the image's, the motors renumbered
            back by the environment. A policy trained so must be exported folded
            (``host-trainer import-rslrl --fold-mirror``) for the controller to fly it.

    Raises:
        ValueError: an unknown task, preset, spawn, row, competition or reward term, a bad number, a
            race without an opponent, or an opponent blob that does not validate.
        OSError: the opponent blob cannot be read (``FileNotFoundError`` when missing).
    """
    env = RustVecEnv(
        task=task,
        num_envs=num_envs,
        preset=preset,
        seed=seed,
        spawn=spawn,
        episode_s=episode_s,
        random_initial_episode_length=random_initial_episode_length,
        opponent=opponent,
        competition=competition,
        competition_weight=competition_weight,
        row=row,
        velocity_scale_mps=velocity_scale_mps,
        spawn_speed_mps=spawn_speed_mps,
        stage1_fraction=stage1_fraction,
        stage2_fraction=stage2_fraction,
        replay_fraction=replay_fraction,
        racing_line_fraction=racing_line_fraction,
        reward_weights=reward_weights,
        fold_mirror=fold_mirror,
    )
    return OvertakeVecEnv(env, task=task)


class OvertakeVecEnv(VectorEnv):
    """Gymnasium ``VectorEnv`` over the Rust environments (build it with :func:`make_vec_env`).

    **Autoreset: same step** (``metadata["autoreset_mode"] = AutoresetMode.SAME_STEP``). An env
    whose episode ends in a step has already restarted: its row of the returned
    observations is the next episode's first. The observation of the state the episode
    ended in is in ``infos["final_obs"]`` (an object array, Gymnasium's convention: that
    observation at the done rows, ``None`` elsewhere; ``infos["_final_obs"]`` masks the done
    rows).

    **Episode ends.** ``terminations``: the ego crashed (gate frame, ground, bounds, a
    collision, a diverged state). ``truncations``: the time limit, or in a race the
    opponent's crash alone (the ego's future was cut short, not its fault): bootstrap these.

    **Actions**: float32 ``[num_envs, 4]`` (``TypeError`` for another dtype, ``ValueError``
    for another shape; nothing is stepped then). They are clipped to [-1, 1] before the motors
    and the reward, and a non-finite value (NaN, ±inf) becomes 0, as the flight controller
    does: such actions are accepted, not refused.

    **infos** of a step (arrays ``[num_envs]``, the step just taken, i.e. for a done env the
    episode's last step): the reward terms ``progress``, ``command``, ``smoothness``,
    ``pass``, ``crash``, ``competition`` (float64 views of one ``[num_envs, 6]`` array, each
    × dt; their sum cast to float32 is the reward), the events ``gate_passed``, ``crashed``, ``timed_out``, ``opponent_crashed``
    (bool), and the final observations above. ``reset`` returns empty infos.

    Every returned array is fresh (a learner may keep it).

    **Gymnasium's wrappers**: episode statistics (``RecordEpisodeStatistics``) and action and
    reward wrappers work; Gymnasium's observation wrappers (``NormalizeObservation``, ...)
    refuse every same-step environment (``VectorObservationWrapper`` accepts only next-step
    or disabled autoreset), so normalise observations in the learner.
    """

    metadata: dict[str, Any] = {"autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, env: RustVecEnv, task: str) -> None:
        self._env = env
        self.task = task
        self.num_envs = env.num_envs
        #: Simulated seconds per step (the control period).
        self.dt_s = env.dt_s
        #: Steps per episode before a time-out.
        self.max_episode_steps = env.max_episode_steps
        # Every value is a clipped term, a unit quaternion's component or a clipped action.
        self.single_observation_space = gym.spaces.Box(
            -1.0, 1.0, shape=(env.obs_dim,), dtype=np.float32
        )
        self.single_action_space = gym.spaces.Box(
            -1.0, 1.0, shape=(ACTION_DIM,), dtype=np.float32
        )
        self.observation_space = gym.vector.utils.batch_space(
            self.single_observation_space, self.num_envs
        )
        self.action_space = gym.vector.utils.batch_space(
            self.single_action_space, self.num_envs
        )

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Every env starts a new episode. With ``seed``, the environments are rebuilt as
        :func:`make_vec_env` with that seed builds them (same spawns, deterministic); without,
        each env draws its next spawn from its own generator. ``options`` is unused."""
        if seed is not None:
            self._np_random_seed = seed
            self._np_random, _ = gym.utils.seeding.np_random(seed)
        return self._env.reset(seed), {}

    def step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        obs, rewards, terminations, truncations = self._env.step(actions)
        info = self._env.step_info()
        terms = info.pop("reward_terms")
        for k, name in enumerate(REWARD_TERMS):
            info[name] = terms[:, k]
        # Gymnasium's same-step convention: an object array, None where the env goes on.
        final_obs = np.empty(self.num_envs, dtype=object)
        rows = info.pop("final_rows")
        final_obs[info.pop("final_index")] = np.fromiter(rows, dtype=object, count=len(rows))
        info["final_obs"] = final_obs
        info["_final_obs"] = terminations | truncations
        return obs, rewards, terminations, truncations, info

    def rollout(self, actions: np.ndarray) -> tuple[np.ndarray, ...]:
        """``T`` steps in one Rust loop (float32 ``[T, num_envs, 4]``, C-contiguous):
        (observations, rewards, dones, timeouts), each stacked over ``T``, straight from the
        Rust environment's accessors. The reference the tests hold :meth:`step` to."""
        return self._env.rollout(actions)

    def close_extras(self, **kwargs: Any) -> None:
        """Nothing to release: the environments are memory only."""
