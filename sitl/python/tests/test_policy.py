"""overtake.Policy: the shipped blobs' means through firmware-core, flying the environment."""

from pathlib import Path

import numpy as np
import pytest

import overtake

POLICIES = Path(__file__).resolve().parents[3] / "policies"
ROW_A = POLICIES / "stage1_guarded.blob"
ROW_G = POLICIES / "stage2_G.blob"


def test_row_a_flies_the_time_trial():
    """The shipped row-A policy, fed the environment's observations (at the blob's velocity
    scale), flies its 15 s episodes from the stage-1 start without a crash and passes gates
    (the referee: 0 crashes, a lap in 10.46 s): a wrong row order or observation layout in
    the binding would crash it."""
    policy = overtake.Policy(ROW_A)
    assert (policy.obs_dim, policy.recurrent, policy.control_period_ns) == (17, False, 20_000_000)
    env = overtake.make_vec_env(num_envs=16, spawn="stage1", policy=policy)
    obs, _ = env.reset(seed=0)
    passed = crashed = 0
    for _ in range(600):
        mean = policy.act(obs)
        assert mean.shape == (16, 4) and mean.dtype == np.float32
        obs, rew, term, trunc, infos = env.step(mean)
        passed += infos["gate_passed"].sum()
        crashed += term.sum()
    assert crashed == 0
    # 12 s of flight at ~0.6 gates/s each.
    assert passed >= 16 * 6, passed


def test_a_folded_policy_flies_in_a_folded_env_only():
    """policies/stage1.blob was trained on observations folded by the track's mirror: in
    an env made with its fold_mirror it flies its 12 s from the stage-1 start without a crash
    through both halves of the figure-8; fed the plain env's observations it crashes."""
    policy = overtake.Policy(POLICIES / "stage1.blob")
    assert policy.fold_mirror and not overtake.Policy(ROW_A).fold_mirror
    outcome = {}
    for fold in [True, False]:
        env = overtake.make_vec_env(
            num_envs=16,
            spawn="stage1",
            velocity_scale_mps=policy.velocity_scale_mps,
            fold_mirror=fold,
        )
        obs, _ = env.reset(seed=0)
        passed = crashed = 0
        for _ in range(600):
            obs, _, term, _, infos = env.step(policy.act(obs))
            passed += infos["gate_passed"].sum()
            crashed += term.sum()
        outcome[fold] = (passed, crashed)
    # Measured: 9 gates each, no crash folded; 32 crashes (two each) plain.
    assert outcome[True][1] == 0 and outcome[True][0] >= 16 * 8, outcome
    # make_vec_env's defaults are the shipped pipeline's observation: it flies there too.
    env = overtake.make_vec_env(num_envs=16, spawn="stage1", random_initial_episode_length=False)
    env.check_policy(policy)
    obs, _ = env.reset(seed=0)
    crashed = 0
    for _ in range(600):
        obs, _, term, _, _ = env.step(policy.act(obs))
        crashed += term.sum()
    assert crashed == 0
    assert outcome[False][1] > 0, outcome


def test_row_a_rows_are_independent():
    policy = overtake.Policy(ROW_A)
    obs = np.random.default_rng(0).uniform(-1, 1, (37, 17)).astype(np.float32)
    batch = policy.act(obs)
    rows = np.concatenate([policy.act(obs[i : i + 1]) for i in range(37)])
    assert np.array_equal(batch, rows)
    assert np.array_equal(policy.act(np.asfortranarray(obs)), batch)


def test_row_g_keeps_a_state_per_row():
    """Row G is recurrent: the same observation twice gives different means; each row's
    state evolves independently of the others (a batch equals single-row policies fed the
    same sequences); `reset(indices)` zeroes only those rows, `reset()` all."""
    rng = np.random.default_rng(1)
    seq = rng.uniform(-1, 1, (5, 8, 30)).astype(np.float32)
    g = overtake.Policy(ROW_G)
    assert (g.obs_dim, g.recurrent) == (30, True)
    singles = [overtake.Policy(ROW_G) for _ in range(8)]
    for t in range(5):
        batch = g.act(seq[t])
        rows = np.concatenate([s.act(seq[t, i : i + 1]) for i, s in enumerate(singles)])
        assert np.array_equal(batch, rows), t
    fresh = overtake.Policy(ROW_G).act(seq[0])
    again = g.act(seq[0])
    assert not np.array_equal(again, fresh)
    g.reset([2, 5])
    after = g.act(seq[0])
    assert np.array_equal(after[[2, 5]], fresh[[2, 5]])
    assert not np.array_equal(after[[0, 1]], fresh[[0, 1]])
    g.reset()
    assert np.array_equal(g.act(seq[0]), fresh)


def test_row_g_races():
    """The shipped row-G ego against the row-A opponent, each row reset when its episode
    ends: it races. Measured here: 23 crashes and 51 gates in 16 × 10 s (0.14 crashes/s;
    the referee's 45 s races: 0.068 /s; training's sampled actions: 0.29 /s). A binding that
    mixed rows, states or layouts crashes nearly every episode and passes no gate."""
    g = overtake.Policy(ROW_G)
    env = overtake.make_vec_env(
        task="race",
        num_envs=16,
        opponent=ROW_A,
        velocity_scale_mps=g.velocity_scale_mps,
    )
    obs, _ = env.reset(seed=0)
    crashes = passed = 0
    for _ in range(500):  # 10 s
        obs, rew, term, trunc, infos = env.step(g.act(obs))
        done = np.flatnonzero(term | trunc)
        if done.size:
            g.reset(done)
        crashes += term.sum()
        passed += infos["gate_passed"].sum()
    assert crashes <= 40 and passed >= 32, (crashes, passed)


def test_bad_policy_arguments_raise(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.blob"):
        overtake.Policy(tmp_path / "missing.blob")
    raw = bytearray(ROW_A.read_bytes())
    raw[-1] ^= 0x40
    (tmp_path / "bad.blob").write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="bad.blob"):
        overtake.Policy(tmp_path / "bad.blob")
    (tmp_path / "garbage.blob").write_bytes(b"OVTK garbage")
    with pytest.raises(ValueError):
        overtake.Policy(tmp_path / "garbage.blob")
    a = overtake.Policy(ROW_A)
    with pytest.raises(ValueError, match=r"shape \(n, 17\)"):
        a.act(np.zeros((4, 30), np.float32))
    with pytest.raises(TypeError, match="float32"):
        a.act(np.zeros((4, 17)))
    g = overtake.Policy(ROW_G)
    g.act(np.zeros((4, 30), np.float32))
    with pytest.raises(ValueError, match="reset"):
        g.act(np.zeros((5, 30), np.float32))
    with pytest.raises(ValueError, match="out of range"):
        g.reset([4])
    g.reset()
    assert g.act(np.zeros((5, 30), np.float32)).shape == (5, 4)
