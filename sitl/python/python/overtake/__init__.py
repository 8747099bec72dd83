"""Overtake's drone-racing simulator as Gymnasium vector environments, and its flash-blob policies.

The environments are ``sitl::env::VecEnv`` (Rust, stepped in parallel with the GIL
released); rewards, episode ends and observations are the Rust environment's, unchanged
(docs/DESIGN.md "Rewards", "Observations"). Two entry points:

- :func:`make_vec_env` builds a :class:`OvertakeVecEnv` (a ``gymnasium.vector.VectorEnv``);
- :class:`Policy` computes a flash blob's actions (its Gaussian means) for batches of
  observations, through firmware-core, the code the flight controller runs.
"""

from __future__ import annotations

import json
import os
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv

from overtake._overtake import ACTION_DIM, Policy, RustVecEnv
from overtake._overtake import shipped_env_json as _shipped_env_json

__all__ = ["ACTION_DIM", "OvertakeVecEnv", "Policy", "make_vec_env", "shipped_env"]

#: The reward's terms, as ``infos`` carries them (each × dt, signed as it enters the reward).
REWARD_TERMS = ("progress", "command", "smoothness", "pass", "crash", "competition")
#: The events of a step, as ``infos`` carries them.
EVENTS = ("gate_passed", "crashed", "timed_out", "opponent_crashed")


def shipped_env(task: str = "time_trial") -> dict[str, Any]:
    """The shipped pipeline's environment for ``task``, as :func:`make_vec_env`'s defaults.

    Returns ``{"env": host-trainer's [env] table, "reward": the reward weights,
    "competition": ..., "competition_weight": ...}``, from ``sitl::env::EnvConfig::stage1``
    (``task="time_trial"``: ``host-trainer/configs/stage1.toml`` without its domain
    randomisation, i.e. ``configs/experiments/stage1_nominal.toml``) or ``EnvConfig::stage2``
    (``task="race"``: the paper's race with the shipped velocity scale). host-trainer's tests
    hold them equal to the shipped configs.
    """
    return json.loads(_shipped_env_json(task))


#: The training curriculum's settings, 0 (the paper's) unless passed (see make_vec_env).
_CURRICULUM = (
    "spawn_speed_mps",
    "stage1_fraction",
    "stage2_fraction",
    "replay_fraction",
)

#: A policy's observation layout by its observation size (rows C-G share the 30 values).
_ROW_OF_DIM = {17: "A", 20: "B", 30: "G"}


def make_vec_env(
    task: str = "time_trial",
    num_envs: int = 1024,
    preset: str | None = None,
    seed: int = 0,
    spawn: str | None = None,
    opponent: str | os.PathLike[str] | None = None,
    episode_s: float | None = None,
    *,
    random_initial_episode_length: bool | None = None,
    competition: str | None = None,
    competition_weight: float | None = None,
    row: str | None = None,
    velocity_scale_mps: float | None = None,
    spawn_speed_mps: float | None = None,
    stage1_fraction: float | None = None,
    stage2_fraction: float | None = None,
    replay_fraction: float | None = None,
    reward_weights: dict[str, float] | None = None,
    fold_mirror: bool | None = None,
    policy: str | os.PathLike[str] | Policy | None = None,
    randomize: str | None = None,
    randomize_share: float = 1.0,
    spawn_jitter: str | None = None,
) -> OvertakeVecEnv:
    """``num_envs`` auto-resetting environments of a time trial or a race.

    **Defaults.** A setting left ``None`` takes the shipped pipeline's value for the task
    (:func:`shipped_env`; ``host-trainer/configs/stage1.toml`` for a time trial, the paper's
    race at the shipped velocity scale for a race): the ``paper`` preset, 15 s episodes with
    random initial lengths, spawns along the track (a race: the stage-2 spawn), the velocity
    observed at 12 m/s full scale and, in a time trial, the track folded by its mirror, so
    that ``policies/stage1.blob`` flies here as it was trained. **Two groups are not the
    shipped config's**, on purpose:

    - the training curriculum (``spawn_speed_mps``, ``stage1_fraction``,
      ``stage2_fraction``, ``replay_fraction``) defaults to 0, the
      paper's: it changes where episodes start, which surprises anyone flying a policy
      rather than training one;
    - the reward weights default to the paper's (``crash`` 5; stage1.toml trains with 1).

    To train as stage1.toml does, pass them: ``make_vec_env(**shipped_env()["env"],
    reward_weights=shipped_env()["reward"])``. The paper's own stage 1 is
    ``spawn="stage1"``, ``velocity_scale_mps=3``, ``fold_mirror=False``.

    Args:
        task: ``"time_trial"`` (stage 1, one drone) or ``"race"`` (stage 2: against
            ``opponent``, spawned as the paper's stage 2; ``spawn`` must be ``"stage2"``).
        num_envs: number of parallel environments (1 to 2**20).
        preset: dynamics preset, ``"paper"``, ``"nominal"`` or ``"realistic"``.
        seed: seed of the spawns (env i draws from stream i); ``reset(seed=s)`` rebuilds
            the environments as if made with ``seed=s``.
        spawn: time-trial spawns, ``"along-track"`` (a uniform point of the centreline),
            ``"stage1"`` (the paper's fixed start) or ``"stage2"`` (2 m before a random gate).
        opponent: race only: path of the opponent's flash blob (a time-trial, row-A policy).
        episode_s: episode length (s) before a time-out.
        random_initial_episode_length: start each env at a random point of its first
            episode (RSL-RL's ``init_at_random_ep_len``), so that time-outs spread out.
        competition: race only: ``"dense"`` (paper eq. 6), ``"sparse"`` (eq. 7) or
            ``"lead"``.
        competition_weight: race only: its weight λ_c (paper 0.5).
        row: Table 1 row whose observation layout to use (``"A"``: 17 values, the default of
            a time trial; ``"B"``: 20; ``"C"``-``"G"``: 30, ``"G"`` the default of a race).
        velocity_scale_mps: the own-velocity scale of the observation (m/s; paper 3, the
            shipped policies 12: ``Policy(path).velocity_scale_mps``).
        spawn_speed_mps: time trial: highest initial speed along the spawn's heading (m/s).
        stage1_fraction: time trial: share of respawns at the paper's fixed start.
        stage2_fraction: time trial: share of the respawns neither replayed nor at the
            fixed start at the paper's stage-2 start (at rest, 2 m or 1 m before a random
            gate), where a stage-1 policy starts as stage 2's opponent.
        replay_fraction: time trial: share of respawns from the state right after one of
            the env's own recent gate passes (when it has one; Song et al. 2023).
        reward_weights: the reward's weights that differ from the paper's, by term name
            (``progress`` 0.5, ``command`` 0.0005, ``smoothness`` 0.0002, ``pass`` 1,
            ``crash`` 5; e.g. ``{"crash": 1.0}``, as ``[reward]`` in host-trainer's configs).
        fold_mirror: observe the figure-8 folded onto one half by its mirror symmetry
            (host-trainer's ``env.fold_mirror``): a step flying to the mirrored half's gates
            observes its mirror image, and its action is the image's, the motors renumbered
            back by the environment. A policy trained so must be exported folded
            (``host-trainer import-rslrl --fold-mirror``) for the controller to fly it.
        randomize: domain randomisation of the ego (host-trainer's ``env.randomize``), in
            ``sitl eval --perturb``'s words, e.g. ``"latency=0:1,motor-tau-ms=0:30,noise=1"``:
            airframe and latency drawn at every spawn, sensor noise on the observed state
            every step (docs/DESIGN.md "Perturbations"). ``None``: the nominal world.
        randomize_share: the share of spawns ``randomize`` draws for, in [0, 1] (the others
            fly the nominal airframe; host-trainer's ``env.randomize_share``).
        spawn_jitter: jitter of the ego's starts (host-trainer's ``env.spawn_jitter``), in
            ``sitl eval --jitter``'s words: ``""`` for ±5 cm, ±5° and ±0.2 m/s per axis, or
            ``"pos=M,att-deg=DEG,vel=MPS"``. ``None``: the spawns exactly.
        policy: a blob path or :class:`Policy`: build the envs that policy observes (its
            layout, velocity scale and fold). A setting passed as well that contradicts it
            is a ``ValueError``.

    Raises:
        ValueError: an unknown task, preset, spawn, row, competition or reward term, a
            setting out of its range (the message names it), a race without an opponent,
            an opponent blob that does not validate, or a ``policy`` that contradicts a
            setting.
        OSError: the opponent blob cannot be read (``FileNotFoundError`` when missing).
    """
    shipped = shipped_env(task) if task in ("time_trial", "race") else shipped_env()
    given = {
        "preset": preset,
        "spawn": spawn,
        "episode_s": episode_s,
        "random_initial_episode_length": random_initial_episode_length,
        "velocity_scale_mps": velocity_scale_mps,
        "spawn_speed_mps": spawn_speed_mps,
        "stage1_fraction": stage1_fraction,
        "stage2_fraction": stage2_fraction,
        "replay_fraction": replay_fraction,
        "fold_mirror": fold_mirror,
    }
    if policy is not None:
        row = _observe_as(policy, given, row)
    defaults = {k: shipped["env"].get(k, 0.0) for k in given}
    defaults.update(dict.fromkeys(_CURRICULUM, 0.0))
    defaults["fold_mirror"] = bool(shipped["env"].get("fold_mirror", False))
    env_settings = {k: defaults[k] if v is None else v for k, v in given.items()}
    env = RustVecEnv(
        task=task,
        num_envs=num_envs,
        seed=seed,
        opponent=opponent,
        competition=shipped["competition"] if competition is None else competition,
        competition_weight=(
            shipped["competition_weight"] if competition_weight is None else competition_weight
        ),
        row=row,
        reward_weights=reward_weights,
        randomize=randomize,
        randomize_share=randomize_share,
        spawn_jitter=spawn_jitter,
        **env_settings,
    )
    return OvertakeVecEnv(env, task=task)


def _observe_as(
    policy: str | os.PathLike[str] | Policy, given: dict[str, Any], row: str | None
) -> str:
    """Sets ``given``'s observation settings to ``policy``'s (refusing a contradiction) and
    returns the row whose layout it observes."""
    p = policy if isinstance(policy, Policy) else Policy(os.fspath(policy))
    own = {"velocity_scale_mps": p.velocity_scale_mps, "fold_mirror": p.fold_mirror}
    for key, value in own.items():
        if given[key] is not None and given[key] != value:
            raise ValueError(
                f"{key}={given[key]!r} contradicts the policy, which observes {key}={value!r}"
            )
        given[key] = value
    policy_row = _ROW_OF_DIM.get(p.obs_dim)
    if policy_row is None:
        raise ValueError(f"policy: {p.obs_dim} observation values is no Table 1 layout")
    if row is not None and {"A": 17, "B": 20}.get(row.upper(), 30) != p.obs_dim:
        raise ValueError(f"row={row!r} contradicts the policy, which observes {p.obs_dim} values")
    return row if row is not None else policy_row


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
    and the reward, and a non-finite value (NaN, ±inf) becomes 0 (the flight controller is
    stricter: it stops the motors): such actions are accepted, not refused, and counted
    (``take_stats()["nonfinite_actions"]``; a learner that sees any has diverged).

    **Policies**: :meth:`check_policy` refuses a :class:`Policy` that observes otherwise
    than these envs (``make_vec_env(policy=...)`` builds the envs a blob expects).

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

    def take_stats(self) -> dict[str, Any]:
        """What happened since the last call, summed over envs, and reset: ``steps``,
        ``gates_passed``, ``crashes``, ``timeouts``, ``opponent_crashes``,
        ``nonfinite_actions`` (int) and each reward term's sum (float)."""
        return self._env.take_stats()

    @property
    def env_settings(self) -> dict[str, Any]:
        """The ``[env]`` settings these envs were built with (host-trainer's table)."""
        return json.loads(self._env.env_json)

    def check_policy(self, policy: Policy) -> None:
        """Raises ``ValueError`` when ``policy`` observes otherwise than these envs (another
        layout, velocity scale or fold), naming every difference: flown here it would see
        observations it was not trained on."""
        self._env.check_policy(policy)

    def rollout(self, actions: np.ndarray) -> tuple[np.ndarray, ...]:
        """``T`` steps in one Rust loop (float32 ``[T, num_envs, 4]``, C-contiguous):
        (observations, rewards, dones, timeouts), each stacked over ``T``, straight from the
        Rust environment's accessors. The reference the tests hold :meth:`step` to."""
        return self._env.rollout(actions)

    def close_extras(self, **kwargs: Any) -> None:
        """Nothing to release: the environments are memory only."""
