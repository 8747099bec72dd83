"""RSL-RL's ``VecEnv`` over overtake's environments, so ``rsl_rl``'s ``OnPolicyRunner`` trains
on them unchanged.

Targets **rsl-rl-lib 2.2.4**: the version the paper's own code (Genesis ``examples/drone``,
``pip install rsl-rl-lib==2.2.4``) trains with, whose ``ActorCritic`` and
``ActorCriticRecurrent`` parameter names (``actor.{2k}``, ``memory_a.rnn.*``, ``std``) are
the ones ``host-trainer import-rslrl`` reads. rsl-rl-lib 3.x renamed the policy
(``alg.policy``) and 4.x and later pass observations as a ``TensorDict``; neither is
supported here.

Needs PyTorch (and rsl-rl-lib to subclass its ``VecEnv``); importing this module without
them raises ``ImportError`` naming what to install. ``overtake`` itself does not need them.
"""

from __future__ import annotations

import os
from typing import Any

try:
    import torch
    from rsl_rl.env import VecEnv as _RslRlVecEnv
except ImportError as e:  # pragma: no cover - exercised only without torch
    raise ImportError(
        "overtake.rslrl needs PyTorch and rsl-rl-lib: "
        "pip install torch rsl-rl-lib==2.2.4"
    ) from e

from overtake import REWARD_TERMS, make_vec_env
from overtake._overtake import ACTION_DIM

__all__ = ["VecEnv", "actor_state_dict", "paper_train_cfg"]


class VecEnv(_RslRlVecEnv):
    """``num_envs`` auto-resetting environments in RSL-RL's interface (torch tensors on
    ``device``; the stepping is Rust's, with the GIL released).

    Keyword arguments are :func:`overtake.make_vec_env`'s (``task``, ``num_envs``,
    ``preset``, ``seed``, ``spawn``, ``opponent``, ``episode_s``, ...).

    ``step`` returns ``(obs, rewards, dones, extras)``: ``dones`` (int64) is a crash or a
    truncation, ``extras["time_outs"]`` (bool) the truncations (a time-out, or in a race the
    opponent's crash alone), which RSL-RL's PPO bootstraps with γ·V;
    ``extras["observations"]`` is empty (the critic sees the actor's observation);
    ``extras["log"]`` carries per-step rates RSL-RL averages into its logs: gates passed and
    crashes per simulated second per env, and each reward term per step.

    ``episode_length_buf`` reads and writes the Rust environment's episode step counters, so
    ``OnPolicyRunner.learn(init_at_random_ep_len=True)`` spreads the time-outs as it does on
    the paper's simulator.
    """

    def __init__(self, *, device: str | torch.device = "cpu", **make_vec_env_kwargs: Any):
        kwargs: dict[str, Any] = {"task": "time_trial", "num_envs": 4096, "seed": 0}
        kwargs.update(make_vec_env_kwargs)
        try:
            gym_env = make_vec_env(**kwargs)
        except TypeError as e:
            raise TypeError(f"unknown environment arguments: {e}") from None
        self._env = gym_env._env
        #: The arguments the environments were built with, every ``[env]`` setting resolved
        #: (RSL-RL logs ``env.cfg``).
        self.cfg: dict[str, Any] = {
            k: os.fspath(v) if k == "opponent" and v is not None else v for k, v in kwargs.items()
        } | gym_env.env_settings
        self.device = torch.device(device)
        self.num_envs: int = self._env.num_envs
        self.num_actions: int = ACTION_DIM
        self.num_obs: int = self._env.obs_dim
        self.max_episode_length: int = self._env.max_episode_steps
        #: Simulated seconds per step.
        self.step_dt: float = self._env.dt_s
        # The observations of the spawns just built (a reset with the construction seed
        # rebuilds the same envs): the same episodes as make_vec_env(seed=...) starts.
        self._obs = self._tensor(self._env.reset(kwargs["seed"]))
        self._totals = _zero_totals()

    def _tensor(self, array: Any) -> torch.Tensor:
        return torch.from_numpy(array).to(self.device)

    @property
    def unwrapped(self) -> VecEnv:
        """This environment (RSL-RL reads ``env.unwrapped.step_dt`` for RND)."""
        return self

    @property
    def episode_length_buf(self) -> torch.Tensor:
        """Steps each env's episode has run (int64 ``[num_envs]``, a fresh copy)."""
        return self._tensor(self._env.episode_steps)

    @episode_length_buf.setter
    def episode_length_buf(self, steps: torch.Tensor) -> None:
        self._env.episode_steps = [int(s) for s in torch.as_tensor(steps).reshape(-1).tolist()]

    def get_observations(self) -> tuple[torch.Tensor, dict[str, Any]]:
        """The current observations (float32 ``[num_envs, obs_dim]``) and empty extras."""
        return self._obs, {"observations": {}}

    def reset(self) -> tuple[torch.Tensor, dict[str, Any]]:
        """Every env starts a new episode from its own generator."""
        self._obs = self._tensor(self._env.reset(None))
        return self._obs, {"observations": {}}

    def step(
        self, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        """One step of every env; ``actions`` ``[num_envs, 4]`` (any float dtype, any
        device: copied to float32 on the CPU), clipped to [-1, 1] by the environment."""
        a = actions.detach().to("cpu", torch.float32).numpy()
        obs, rewards, terminated, truncated = self._env.step(a)
        self._obs = self._tensor(obs)
        dones = torch.from_numpy(terminated | truncated).to(self.device, torch.long)
        time_outs = torch.from_numpy(truncated).to(self.device)
        stats = self._env.take_stats()
        for k in self._totals:
            self._totals[k] += stats[k]
        per_s = 1.0 / (max(stats["steps"], 1) * self.step_dt)
        log = {
            "/gates_per_s": stats["gates_passed"] * per_s,
            "/crashes_per_s": stats["crashes"] * per_s,
        }
        for name in REWARD_TERMS:
            log[f"/reward/{name}"] = stats[name] / max(stats["steps"], 1)
        extras = {"observations": {}, "time_outs": time_outs, "log": log}
        return self._obs, self._tensor(rewards), dones, extras

    def set_reward_weights(self, weights: dict[str, float]) -> None:
        """The reward's weights from the next step on: the paper's with the named ones
        replaced (as ``reward_weights``); a schedule such as host-trainer's ``[pass_decay]``
        calls it between rollouts. ``ValueError`` for an unknown term or a bad weight."""
        self._env.set_reward_weights(weights)

    def reward_weights(self) -> dict[str, float]:
        """The reward's weights now, by term name."""
        return self._env.reward_weights()

    def take_totals(self) -> dict[str, float]:
        """Sums since the last call (``steps``, the events ``gates_passed``, ``crashes``,
        ``timeouts``, ``opponent_crashes`` and each reward term), and reset: a training
        script's per-iteration log."""
        t, self._totals = self._totals, _zero_totals()
        return t

    def close(self) -> None:
        """Nothing to release: the environments are memory only."""


def _zero_totals() -> dict[str, float]:
    keys = ["steps", "gates_passed", "crashes", "timeouts", "opponent_crashes", *REWARD_TERMS]
    return dict.fromkeys(keys, 0)


def paper_train_cfg(row: str = "A") -> dict[str, Any]:
    """RSL-RL's train config for a Table 1 row with the paper's PPO (docs/DESIGN.md
    "Learning"): clip 0.2, γ 0.99, λ 0.95, 5 epochs × 4 minibatches, 100 steps per env,
    adaptive lr from KL 0.01, grad norm 1.0, clipped value loss, std 1.0, tanh. Row A: MLP
    2×128, lr 1e-4, entropy 0.01. Row G: 2-layer LSTM 128 → MLP 256,128,128,64, lr 1e-5,
    entropy 0.008. Rows E (1-layer LSTM + 4-layer MLP) and F (2-layer LSTM + MLP
    256,128,128) as Table 1 has them.

    A fresh dict each call (``OnPolicyRunner`` pops ``class_name`` from it)."""
    row = row.upper()
    recurrent = {
        "E": (1, [256, 128, 128, 64]),
        "F": (2, [256, 128, 128]),
        "G": (2, [256, 128, 128, 64]),
    }
    if row == "A":
        policy: dict[str, Any] = {
            "class_name": "ActorCritic",
            "actor_hidden_dims": [128, 128],
            "critic_hidden_dims": [128, 128],
        }
        lr, entropy = 1e-4, 0.01
    elif row in recurrent:
        layers, hidden = recurrent[row]
        policy = {
            "class_name": "ActorCriticRecurrent",
            "actor_hidden_dims": hidden,
            "critic_hidden_dims": hidden,
            "rnn_type": "lstm",
            "rnn_hidden_size": 128,
            "rnn_num_layers": layers,
        }
        lr, entropy = 1e-5, 0.008
    else:
        raise ValueError(f"row '{row}': RSL-RL configs exist for rows A, E, F and G")
    policy.update({"activation": "tanh", "init_noise_std": 1.0})
    return {
        "algorithm": {
            "class_name": "PPO",
            "clip_param": 0.2,
            "desired_kl": 0.01,
            "entropy_coef": entropy,
            "gamma": 0.99,
            "lam": 0.95,
            "learning_rate": lr,
            "max_grad_norm": 1.0,
            "num_learning_epochs": 5,
            "num_mini_batches": 4,
            "schedule": "adaptive",
            "use_clipped_value_loss": True,
            "value_loss_coef": 1.0,
        },
        "policy": policy,
        "num_steps_per_env": 100,
        "save_interval": 100,
        "empirical_normalization": False,
    }


def actor_state_dict(actor_critic: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The actor's tensors of an RSL-RL ``ActorCritic`` / ``ActorCriticRecurrent`` under
    RSL-RL's names (``actor.*``, ``memory_a.*``, ``std``), contiguous float32 on the CPU:
    what ``host-trainer import-rslrl`` reads (save it with ``safetensors.torch.save_file``)."""
    keep = ("actor.", "memory_a.", "std", "log_std")
    return {
        k: v.detach().to("cpu", torch.float32).contiguous()
        for k, v in actor_critic.state_dict().items()
        if k.startswith(keep)
    }
