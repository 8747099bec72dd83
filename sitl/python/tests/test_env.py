"""The Gymnasium vector environment over sitl::env::VecEnv: spaces, autoreset, determinism,
parity with the Rust loop, the reward terms in infos, and refused arguments."""

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import overtake

POLICIES = Path(__file__).resolve().parents[3] / "policies"
OPPONENT = POLICIES / "stage1_guarded.blob"
DT = 0.02


def actions(rng, n, t=None, scale=1.2):
    """Random actions around hover, some beyond [-1, 1] (the env clips them)."""
    shape = (n, 4) if t is None else (t, n, 4)
    return (0.5 + scale * rng.standard_normal(shape)).astype(np.float32)


@pytest.fixture(params=["time_trial", "race"])
def task(request):
    return request.param


def make(task, **kw):
    if task == "race":
        kw.setdefault("opponent", OPPONENT)
    return overtake.make_vec_env(task=task, **kw)


def test_spaces_and_dtypes(task):
    env = make(task, num_envs=8)
    dim = 17 if task == "time_trial" else 30
    assert isinstance(env, gym.vector.VectorEnv)
    assert env.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP
    assert env.single_observation_space == gym.spaces.Box(-1, 1, (dim,), np.float32)
    assert env.single_action_space == gym.spaces.Box(-1, 1, (4,), np.float32)
    assert env.observation_space.shape == (8, dim)
    assert env.action_space.shape == (8, 4)
    assert env.observation_space.dtype == env.action_space.dtype == np.float32
    obs, infos = env.reset(seed=0)
    assert obs.shape == (8, dim) and obs.dtype == np.float32 and infos == {}
    obs, rew, term, trunc, infos = env.step(env.action_space.sample())
    assert obs.dtype == rew.dtype == np.float32 and rew.shape == (8,)
    assert term.dtype == trunc.dtype == np.bool_ and term.shape == trunc.shape == (8,)
    for k in overtake.REWARD_TERMS:
        assert infos[k].shape == (8,) and infos[k].dtype == np.float64
    for k in overtake.EVENTS:
        assert infos[k].shape == (8,) and infos[k].dtype == np.bool_


def test_observations_stay_in_the_space(task):
    env = make(task, num_envs=64, episode_s=2.0)
    obs, _ = env.reset(seed=3)
    rng = np.random.default_rng(0)
    for _ in range(150):
        assert env.observation_space.contains(obs)
        obs, *_ = env.step(actions(rng, 64))


def test_the_python_step_is_the_rust_loop(task):
    """Parity: `step` through Python (actions in a Fortran-ordered array, so the binding's
    strided path is exercised) gives bit-identical observations, rewards and episode ends to
    the same environment stepped T times inside Rust; terminations and truncations split the
    Rust dones as its timeouts say, and episodes do end in the run."""
    n, t = 32, 300
    rng = np.random.default_rng(1)
    acts = actions(rng, n, t)
    acts[5, 3, 1] = np.nan
    a = make(task, num_envs=n, seed=7, episode_s=1.0)
    b = make(task, num_envs=n, seed=7, episode_s=1.0)
    obs0, _ = a.reset(seed=7)
    obs0b, _ = b.reset(seed=7)
    assert np.array_equal(obs0, obs0b)
    r_obs, r_rew, r_done, r_timeout = b.rollout(acts)
    for k in range(t):
        obs, rew, term, trunc, _ = a.step(np.asfortranarray(acts[k]))
        assert np.array_equal(obs, r_obs[k]), k
        assert np.array_equal(rew, r_rew[k]), k
        assert np.array_equal(term, r_done[k] & ~r_timeout[k]), k
        assert np.array_equal(trunc, r_timeout[k]), k
    assert r_done.sum() > n and (r_done & ~r_timeout).any() and r_timeout.any()


def test_rows_are_independent_envs():
    """Row i of a batch is env i: a batch stepped with per-row actions equals single-env
    batches stepped with each row's actions (stage-1 spawns, the same start for all)."""
    n, t = 6, 120
    rng = np.random.default_rng(2)
    acts = actions(rng, n, t, scale=0.3)
    batch = overtake.make_vec_env(num_envs=n, spawn="stage1")
    singles = [overtake.make_vec_env(num_envs=1, spawn="stage1") for _ in range(n)]
    for k in range(t):
        obs, rew, term, trunc, _ = batch.step(acts[k])
        for i, s in enumerate(singles):
            o, r, te, tr, _ = s.step(acts[k, i : i + 1])
            assert np.array_equal(obs[i : i + 1], o) and np.array_equal(rew[i : i + 1], r)
            assert (term[i], trunc[i]) == (te[0], tr[0])


def test_reset_with_a_seed_is_deterministic(task):
    env = make(task, num_envs=16, random_initial_episode_length=True)
    rng = np.random.default_rng(4)
    acts = actions(rng, 16, 50)

    def run(seed):
        out = [env.reset(seed=seed)[0]]
        for a in acts:
            obs, rew, term, trunc, _ = env.step(a)
            out += [obs, rew, term, trunc]
        return out

    first, again, other = run(5), run(5), run(6)
    assert all(np.array_equal(x, y) for x, y in zip(first, again))
    assert not np.array_equal(first[0], other[0])


def test_a_construction_seed_equals_a_reset_seed(task):
    a = make(task, num_envs=16, seed=5)
    b = make(task, num_envs=16, seed=0)
    obs_b, _ = b.reset(seed=5)
    rng = np.random.default_rng(8)
    acts = actions(rng, 16)
    # `a` not reset: its construction already spawned with seed 5.
    assert np.array_equal(a.step(acts)[0], b.step(acts)[0])
    assert obs_b.shape == (16, a.single_observation_space.shape[0])


def test_reset_without_a_seed_starts_new_episodes():
    env = overtake.make_vec_env(num_envs=8, seed=0, random_initial_episode_length=True)
    first, _ = env.reset()
    second, _ = env.reset()
    assert not np.array_equal(first, second)
    # New episodes: the previous action (indices 13..17) is zero after a spawn.
    env.step(np.full((8, 4), 0.5, np.float32))
    assert np.all(env.reset()[0][:, 13:17] == 0)


def test_same_step_autoreset_and_final_observations():
    """A fall from the stage-1 start: the crash step terminates, its returned observation is
    already the respawn's (the start), and infos carry the crashed state's observation in
    Gymnasium's same-step `final_obs`; a hover times out as a truncation."""
    env = overtake.make_vec_env(
        num_envs=2, spawn="stage1", episode_s=0.5, random_initial_episode_length=False
    )
    start, _ = env.reset(seed=0)
    hover = 0.519
    a = np.array([[-1.0] * 4, [hover] * 4], np.float32)
    for k in range(1, 26):
        obs, rew, term, trunc, infos = env.step(a)
        if term[0]:
            break
        assert infos["_final_obs"].tolist() == [False, trunc[1]]
    assert term[0] and not trunc[0] and infos["crashed"][0]
    assert np.array_equal(obs[0], start[0])
    final = infos["final_obs"][0]
    assert final.dtype == np.float32 and final.shape == (17,)
    assert not np.array_equal(final, start[0])
    assert infos["final_obs"][1] is None
    # The state it ended in: below the spawn, at the previous (clipped) action -1.
    assert np.all(final[13:17] == -1.0)
    assert infos["crash"][0] == pytest.approx(-DT * 5.0)
    while not trunc[1]:
        obs, rew, term, trunc, infos = env.step(a)
    assert not term[1] and infos["timed_out"][1] and not infos["crashed"][1]
    assert infos["_final_obs"][1] and np.array_equal(obs[1], start[1])


def test_reward_weights_replace_the_papers_by_name():
    """The fall of the test above with the crash weight at 1 and the progress weight at 0:
    the crash costs dt·1 instead of dt·5, progress pays nothing, the other terms are the
    paper's (the same falling steps, the same command and smoothness terms)."""
    a = np.full((1, 4), -1.0, np.float32)
    runs = {}
    for weights in [None, {"crash": 1.0, "progress": 0.0}]:
        env = overtake.make_vec_env(num_envs=1, spawn="stage1", reward_weights=weights)
        env.reset(seed=0)
        steps = []
        while True:
            _, _, term, _, infos = env.step(a)
            steps.append({k: float(infos[k][0]) for k in ("progress", "command", "crash")})
            if term[0]:
                break
        runs[weights is None] = steps
    paper, changed = runs[True], runs[False]
    assert len(paper) == len(changed)
    assert paper[-1]["crash"] == pytest.approx(-DT * 5.0)
    assert changed[-1]["crash"] == pytest.approx(-DT * 1.0)
    assert any(s["progress"] != 0.0 for s in paper)
    assert all(s["progress"] == 0.0 for s in changed)
    assert [s["command"] for s in paper] == [s["command"] for s in changed]


def test_reward_weights_set_between_steps_take_effect_and_survive_a_reset():
    """set_reward_weights (a trainer's schedule, host-trainer's [pass_decay]) changes the
    weights from the next step on, as the constructor's would, and a seeded reset keeps
    them; a bad weight is refused and changes nothing."""
    a = np.full((1, 4), -1.0, np.float32)

    def fall(env):
        env.reset(seed=0)
        while True:
            _, _, term, _, infos = env.step(a)
            if term[0]:
                return float(infos["crash"][0])

    env = overtake.make_vec_env(num_envs=1, spawn="stage1")
    assert env._env.reward_weights()["crash"] == pytest.approx(5.0)
    assert fall(env) == pytest.approx(-DT * 5.0)
    env._env.set_reward_weights({"crash": 1.0})
    assert env._env.reward_weights()["crash"] == pytest.approx(1.0)
    assert env._env.reward_weights()["progress"] == pytest.approx(0.5)
    assert fall(env) == pytest.approx(-DT * 1.0)  # fall() resets with a seed first
    with pytest.raises(ValueError, match="unknown term 'crsh'"):
        env._env.set_reward_weights({"crsh": 2.0})
    with pytest.raises(ValueError, match="reward.crash: -1"):
        env._env.set_reward_weights({"crash": -1.0})
    assert env._env.reward_weights()["crash"] == pytest.approx(1.0)


def test_fold_mirror_folds_the_mirrored_half_only():
    """With fold_mirror the envs flying to the mirrored half observe their mirror image
    (host-trainer's env.fold_mirror): from the same spawns, some rows differ from the plain
    env's and the others are equal, and so they stay under the same (symmetric) actions."""
    plain = overtake.make_vec_env(num_envs=64, seed=3, fold_mirror=False)
    folded = overtake.make_vec_env(num_envs=64, seed=3, fold_mirror=True)
    p, _ = plain.reset(seed=3)
    f, _ = folded.reset(seed=3)
    same = np.all(p == f, axis=1)
    assert same.any() and not same.all()
    hover = np.full((64, 4), 0.1, np.float32)  # equal motors: the image's action is the same
    p, *_ = plain.step(hover)
    f, *_ = folded.step(hover)
    assert np.array_equal(p[same], f[same])
    assert not np.array_equal(p, f)


def test_reward_terms_add_up_and_match_numpy():
    """The reward is the terms' sum; the command and smoothness terms recomputed in numpy
    from the clipped actions (a swapped or mislabelled term fails here)."""
    n = 64
    env = overtake.make_vec_env(num_envs=n, seed=2, fold_mirror=False)
    env.reset(seed=2)
    rng = np.random.default_rng(3)
    prev = np.zeros((n, 4))
    for _ in range(400):
        a = actions(rng, n, scale=0.4)
        obs, rew, term, trunc, infos = env.step(a)
        total = sum(infos[k] for k in overtake.REWARD_TERMS)
        assert np.array_equal(total.astype(np.float32), rew)
        c = np.clip(a, -1, 1).astype(np.float64)
        assert np.allclose(infos["command"], -DT * 0.0005 * np.linalg.norm(c, axis=1), rtol=1e-5)
        assert np.allclose(infos["smoothness"], -DT * 0.0002 * ((c - prev) ** 2).sum(1), rtol=1e-4, atol=1e-12)
        assert np.all(infos["competition"] == 0)
        assert np.array_equal(infos["crash"] != 0, infos["crashed"])
        assert np.array_equal(infos["crashed"], term)
        assert np.all(infos["pass"][~infos["gate_passed"]] == 0)
        prev = np.where((term | trunc)[:, None], 0.0, c)


def test_non_finite_actions_are_zero():
    a = overtake.make_vec_env(num_envs=3, seed=1)
    b = overtake.make_vec_env(num_envs=3, seed=1)
    bad = np.array([[np.nan, np.inf, -np.inf, 0.3]] * 3, np.float32)
    good = np.array([[0, 0, 0, 0.3]] * 3, np.float32)
    for x, y in zip(a.step(bad)[:4], b.step(good)[:4]):
        assert np.array_equal(x, y)
    assert a.take_stats()["nonfinite_actions"] == 9
    assert b.take_stats()["nonfinite_actions"] == 0


def test_race_events():
    """A hovering ego: the opponent flies off, and any episode end is the opponent's crash
    (a truncation), never the ego's; the competition term is paid."""
    env = make("race", num_envs=16, seed=11, competition="lead", random_initial_episode_length=False)
    obs, _ = env.reset(seed=11)
    hover = np.full((16, 4), 0.519, np.float32)
    for _ in range(100):
        obs, rew, term, trunc, infos = env.step(hover)
        assert not term.any()
        assert np.array_equal(trunc, infos["opponent_crashed"])
        assert np.all(infos["competition"] != 0)


@pytest.mark.parametrize(
    "kw, exc, text",
    [
        ({"task": "sprint"}, ValueError, "task 'sprint'"),
        ({"preset": "fast"}, ValueError, "preset 'fast'"),
        ({"spawn": "stage3"}, ValueError, "spawn 'stage3'"),
        ({"task": "race", "opponent": str(OPPONENT), "spawn": "along-track"}, ValueError, "spawn: 'along-track'"),
        ({"velocity_scale_mps": 0.0}, ValueError, "velocity_scale_mps: 0"),
        ({"num_envs": 0}, ValueError, "num_envs"),
        ({"num_envs": -3}, ValueError, "num_envs"),
        ({"num_envs": 10**12}, ValueError, "num_envs"),
        ({"episode_s": float("nan")}, ValueError, "episode_s"),
        ({"row": "G"}, ValueError, "row G"),
        ({"row": "Z"}, ValueError, "row 'Z'"),
        ({"replay_fraction": 1.5}, ValueError, "replay_fraction: 1.5"),
        ({"stage2_fraction": -0.1}, ValueError, "stage2_fraction: -0.1"),
        ({"reward_weights": {"crsh": 1.0}}, ValueError, "unknown term 'crsh'"),
        ({"reward_weights": {"crash": -1.0}}, ValueError, "reward.crash: -1"),
        ({"reward_weights": {"pass": float("inf")}}, ValueError, "reward.pass: inf"),
        ({"opponent": str(OPPONENT)}, ValueError, "no opponent"),
        ({"task": "race"}, ValueError, "needs an opponent"),
        ({"task": "race", "opponent": str(OPPONENT), "competition": "x"}, ValueError, "competition 'x'"),
        ({"task": "race", "opponent": "/nonexistent.blob"}, FileNotFoundError, "/nonexistent.blob"),
        ({"task": "race", "opponent": str(POLICIES / "stage2_G.blob")}, ValueError, "observes an opponent"),
        ({"randomize": "mass=-1"}, ValueError, "randomize: mass: must lie in"),
        ({"randomize": "gravity=2"}, ValueError, "unknown perturbation 'gravity'"),
        ({"randomize": "noise=1", "randomize_share": 1.5}, ValueError, "randomize_share"),
        ({"spawn_jitter": "pos=-1"}, ValueError, "spawn_jitter"),
        ({"spawn_jitter": "wobble=1"}, ValueError, "spawn_jitter: --jitter: unknown key 'wobble'"),
    ],
)
def test_bad_arguments_raise(kw, exc, text):
    with pytest.raises(exc, match=text):
        overtake.make_vec_env(**kw)


def test_spawn_jitter_moves_the_starts():
    """``spawn_jitter`` moves the ego's starts (its first observations differ from the exact
    spawns'); the same seed jitters them alike."""
    exact = overtake.make_vec_env(num_envs=8, seed=3, spawn_speed_mps=0.0)
    jittered = overtake.make_vec_env(num_envs=8, seed=3, spawn_speed_mps=0.0, spawn_jitter="")
    again = overtake.make_vec_env(num_envs=8, seed=3, spawn_speed_mps=0.0, spawn_jitter="")
    o1, _ = exact.reset(seed=3)
    o2, _ = jittered.reset(seed=3)
    o3, _ = again.reset(seed=3)
    assert not np.array_equal(o1, o2)
    np.testing.assert_array_equal(o2, o3)


def test_randomize_changes_the_observations_not_the_flight():
    """Sensor noise (``randomize="noise=1"``) reaches the observations; the rewards, judged
    on the true state, are the nominal ones."""
    nominal = overtake.make_vec_env(num_envs=8, seed=3)
    noisy = overtake.make_vec_env(num_envs=8, seed=3, randomize="noise=1")
    o1, _ = nominal.reset(seed=3)
    o2, _ = noisy.reset(seed=3)
    assert not np.array_equal(o1, o2)
    assert np.abs(o1 - o2).max() < 0.5
    hover = np.full((8, 4), 0.519, np.float32)
    for _ in range(20):
        _, r1, *_ = nominal.step(hover)
        _, r2, *_ = noisy.step(hover)
        assert np.array_equal(r1, r2)


def test_a_corrupt_opponent_is_refused(tmp_path):
    raw = bytearray(OPPONENT.read_bytes())
    raw[-1] ^= 0x40
    bad = tmp_path / "bad.blob"
    bad.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="opponent '.*bad.blob': blob CRC"):
        overtake.make_vec_env(task="race", opponent=bad)
    with pytest.raises(OSError):
        overtake.make_vec_env(task="race", opponent=tmp_path)


def test_bad_actions_raise_and_step_nothing():
    env = overtake.make_vec_env(num_envs=4, seed=0)
    obs, _ = env.reset(seed=0)
    with pytest.raises(TypeError, match="float32"):
        env.step(np.zeros((4, 4), np.float64))
    with pytest.raises(TypeError, match="numpy"):
        env.step([[0.0] * 4] * 4)
    with pytest.raises(ValueError, match=r"shape \(4, 4\)"):
        env.step(np.zeros((3, 4), np.float32))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(16, np.float32))
    # Nothing moved: the next step equals a fresh env's first.
    fresh = overtake.make_vec_env(num_envs=4, seed=0)
    a = np.full((4, 4), 0.5, np.float32)
    assert np.array_equal(env.step(a)[0], fresh.step(a)[0])


def test_strided_actions_are_read_in_logical_order():
    """Actions in any memory order step the same: C order, Fortran order, and a strided view
    (numpy's `as_slice` accepts Fortran memory as contiguous; reading it raw mixes rows)."""
    rng = np.random.default_rng(9)
    big = actions(rng, 10, scale=0.5).repeat(2, axis=1).reshape(10, 8)
    views = [np.ascontiguousarray(big[:, ::2]), np.asfortranarray(big[:, ::2]), big[:, ::2]]
    outs = [overtake.make_vec_env(num_envs=10, seed=4).step(v)[0] for v in views]
    assert np.array_equal(outs[0], outs[1]) and np.array_equal(outs[0], outs[2])


def test_gymnasium_wrappers_see_the_episodes():
    """Gymnasium's own episode statistics over this env: hovering envs of 0.5 s episodes
    (25 steps) all end at step 25 with the summed reward; action wrappers apply."""
    env = overtake.make_vec_env(
        num_envs=8, spawn="stage1", episode_s=0.5, random_initial_episode_length=False
    )
    stats = gym.wrappers.vector.RecordEpisodeStatistics(env)
    stats.reset(seed=0)
    total = np.zeros(8)
    for k in range(25):
        _, rew, term, trunc, infos = stats.step(np.full((8, 4), 0.519, np.float32))
        total += rew
    assert trunc.all() and not term.any()
    assert infos["_episode"].all() and np.all(infos["episode"]["l"] == 25)
    assert np.allclose(infos["episode"]["r"], total, rtol=1e-5)
    clipped = gym.wrappers.vector.ClipAction(overtake.make_vec_env(num_envs=8))
    clipped.reset(seed=0)
    assert clipped.step(np.full((8, 4), 7.0, np.float32))[1].shape == (8,)


def test_episode_steps_are_read_and_written():
    """RSL-RL's init_at_random_ep_len writes the episode counters: an env one step short of
    the limit truncates at its next step, the others go on; a bad write changes nothing."""
    env = make("time_trial", num_envs=3, spawn="stage1", random_initial_episode_length=False)
    raw = env._env
    limit = raw.max_episode_steps
    hover = np.full((3, 4), 0.5, np.float32)
    raw.step(hover)
    assert raw.episode_steps.tolist() == [1, 1, 1]
    assert raw.episode_steps.dtype == np.int64
    with pytest.raises(ValueError, match="one per env"):
        raw.episode_steps = [0, 0]
    with pytest.raises(ValueError, match="episode step count -1"):
        raw.episode_steps = [0, -1, 0]
    assert raw.episode_steps.tolist() == [1, 1, 1]
    raw.episode_steps = [limit - 1, 5, 0]
    _, _, terminated, truncated = raw.step(hover)
    assert truncated.tolist() == [True, False, False]
    assert not terminated.any()
    assert raw.episode_steps.tolist() == [0, 6, 1]


def test_take_stats_counts_what_step_info_reports():
    env = make("time_trial", num_envs=64, seed=3)
    env._env.take_stats()
    rng = np.random.default_rng(0)
    gates = crashes = steps = 0
    progress = 0.0
    for _ in range(300):
        _, _, term, _, info = env.step(actions(rng, 64, scale=0.3))
        gates += int(info["gate_passed"].sum())
        crashes += int(term.sum())
        progress += float(info["progress"].sum())
        steps += 64
    s = env._env.take_stats()
    assert crashes > 0
    assert (s["steps"], s["gates_passed"], s["crashes"]) == (steps, gates, crashes)
    assert s["progress"] == pytest.approx(progress, rel=1e-9, abs=1e-12)
    assert env._env.take_stats()["steps"] == 0


def test_defaults_are_the_shipped_environment():
    """make_vec_env's defaults are the shipped pipeline's (``shipped_env``, which host-trainer's
    tests hold equal to configs/stage1.toml and the row-G race), except the curriculum shares
    (0) and the reward (the paper's), as its docstring says."""
    for task in ("time_trial", "race"):
        shipped = overtake.shipped_env(task)
        env = make(task, num_envs=2)
        settings = env.env_settings
        curriculum = {"spawn_speed_mps", "stage1_fraction", "stage2_fraction", "replay_fraction"}
        for key, value in shipped["env"].items():
            if key == "num_envs":
                continue
            expected = 0.0 if key in curriculum else value
            assert settings.get(key, 0.0) == expected, (task, key)
        assert env._env.reward_weights()["crash"] == pytest.approx(5.0)
    stage1 = overtake.shipped_env("time_trial")
    assert stage1["env"]["velocity_scale_mps"] == 12.0 and stage1["env"]["fold_mirror"]
    assert stage1["reward"]["crash"] == 1.0
    # Every default round-trips: the settings the env reports build the same env.
    env = overtake.make_vec_env(num_envs=4, seed=5)
    again = overtake.make_vec_env(num_envs=4, seed=5, **{
        k: v for k, v in env.env_settings.items() if k != "num_envs"
    })
    assert again.env_settings == env.env_settings
    assert np.array_equal(env.reset(seed=5)[0], again.reset(seed=5)[0])


def test_the_envs_a_policy_expects():
    """``policy=`` builds the envs a blob observes; a contradicting setting is refused, and
    ``check_policy`` refuses a policy in envs that observe otherwise."""
    stage1 = overtake.Policy(POLICIES / "stage1.blob")
    paper = overtake.make_vec_env(num_envs=2, velocity_scale_mps=3.0, fold_mirror=False)
    with pytest.raises(ValueError, match="velocity_scale_mps.*fold_mirror"):
        paper.check_policy(stage1)
    built = overtake.make_vec_env(num_envs=2, policy=POLICIES / "stage1_imitation.blob")
    assert not built.env_settings.get("fold_mirror", False)
    built.check_policy(overtake.Policy(POLICIES / "stage1_imitation.blob"))
    with pytest.raises(ValueError, match="contradicts the policy"):
        overtake.make_vec_env(num_envs=2, fold_mirror=False, policy=stage1)
    race = make("race", num_envs=2, policy=POLICIES / "stage2_G.blob")
    race.check_policy(overtake.Policy(POLICIES / "stage2_G.blob"))
    with pytest.raises(ValueError, match="layout"):
        race.check_policy(stage1)
