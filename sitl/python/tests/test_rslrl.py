"""overtake.rslrl: RSL-RL's VecEnv interface over the Rust environments, and one real
OnPolicyRunner iteration on it. Needs PyTorch and rsl-rl-lib 2.2.4: skipped without them
(CI has neither; `tools/train_rslrl.py` runs the full round trip)."""

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("rsl_rl")

import overtake  # noqa: E402
from overtake.rslrl import VecEnv, actor_state_dict, paper_train_cfg  # noqa: E402

OPPONENT = Path(__file__).resolve().parents[3] / "policies" / "stage1_guarded.blob"


def test_the_interface_rsl_rl_reads():
    env = VecEnv(num_envs=16, seed=2)
    obs, extras = env.get_observations()
    assert obs.shape == (16, 17) and obs.dtype == torch.float32
    assert extras == {"observations": {}}
    assert (env.num_envs, env.num_actions, env.num_obs) == (16, 4, 17)
    assert env.max_episode_length == 750
    assert env.step_dt == pytest.approx(0.02)
    assert env.unwrapped is env
    obs, rewards, dones, extras = env.step(torch.full((16, 4), 0.5))
    assert obs.shape == (16, 17) and rewards.shape == (16,) and rewards.dtype == torch.float32
    assert dones.dtype == torch.long and extras["time_outs"].dtype == torch.bool
    assert set(extras["log"]) >= {"/gates_per_s", "/crashes_per_s", "/reward/progress"}


def test_the_same_steps_as_the_gymnasium_env():
    """Bit-identical to make_vec_env for the same seed and actions; dones = terminated or
    truncated, time_outs = truncated."""
    rsl = VecEnv(num_envs=32, seed=5, episode_s=0.5)
    gym_env = overtake.make_vec_env(num_envs=32, seed=5, episode_s=0.5)
    gym_env.reset(seed=5)
    rng = np.random.default_rng(1)
    for _ in range(60):
        a = (0.5 + 0.6 * rng.standard_normal((32, 4))).astype(np.float32)
        obs, rew, dones, extras = rsl.step(torch.from_numpy(a))
        g_obs, g_rew, term, trunc, _ = gym_env.step(a)
        assert np.array_equal(obs.numpy(), g_obs) and np.array_equal(rew.numpy(), g_rew)
        assert np.array_equal(dones.numpy().astype(bool), term | trunc)
        assert np.array_equal(extras["time_outs"].numpy(), trunc)


def test_episode_length_buf_round_trips():
    env = VecEnv(num_envs=4, seed=0)
    env.episode_length_buf = torch.tensor([749, 3, 0, 10])
    assert env.episode_length_buf.tolist() == [749, 3, 0, 10]
    _, _, dones, extras = env.step(torch.full((4, 4), 0.5))
    assert extras["time_outs"].tolist() == [True, False, False, False]
    assert env.episode_length_buf.tolist() == [0, 4, 1, 11]


def test_unknown_environment_arguments_are_refused():
    with pytest.raises(TypeError, match="num_env"):
        VecEnv(num_env=4)


def test_the_learning_levers_reach_the_environment():
    """Replay spawns and reward weights pass through to make_vec_env (and its checks)."""
    env = VecEnv(num_envs=4, replay_fraction=0.3, reward_weights={"crash": 1.0})
    assert env.cfg["replay_fraction"] == 0.3 and env.cfg["reward_weights"] == {"crash": 1.0}
    with pytest.raises(ValueError, match="unknown term"):
        VecEnv(num_envs=4, reward_weights={"crsh": 1.0})


@pytest.mark.parametrize("row", ["A", "G"])
def test_one_runner_iteration_and_the_actor_names(row, tmp_path):
    from rsl_rl.runners import OnPolicyRunner

    torch.manual_seed(0)
    kw = {"task": "race", "opponent": OPPONENT, "row": row} if row != "A" else {}
    env = VecEnv(num_envs=32, seed=0, **kw)
    cfg = paper_train_cfg(row)
    cfg["num_steps_per_env"] = 8
    runner = OnPolicyRunner(env, cfg, log_dir=str(tmp_path), device="cpu")
    before = {k: v.clone() for k, v in actor_state_dict(runner.alg.actor_critic).items()}
    runner.learn(1)
    after = actor_state_dict(runner.alg.actor_critic)
    assert set(after) == set(before)
    assert "std" in after and any(k.startswith("actor.0.") for k in after)
    assert (row == "G") == any(k.startswith("memory_a.rnn.") for k in after)
    assert any(not torch.equal(before[k], after[k]) for k in after), "the update moved nothing"
    assert env.take_totals()["steps"] == 32 * 8
