"""tools/train_rslrl.py: a run killed after its checkpoint resumes where the checkpoint
left it. Needs PyTorch and rsl-rl-lib 2.2.4 (skipped without them, as in CI) and runs the
script's cargo steps (export, parity, referee) twice: about a minute with built binaries."""

import importlib.util
import json
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("rsl_rl")

SCRIPT = Path(__file__).resolve().parents[3] / "tools" / "train_rslrl.py"


def load_script():
    spec = importlib.util.spec_from_file_location("train_rslrl", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_killed_run_resumes_from_its_checkpoint(tmp_path, monkeypatch):
    script = load_script()
    out = tmp_path / "run"
    small = ["--out", str(out), "--num-envs", "16", "--steps-per-env", "8",
             "--eval-episodes", "1", "--parity-envs", "8", "--parity-steps", "20"]  # fmt: skip
    assert script.main(small + ["--iterations", "2", "--checkpoint-every", "2"]) == 0
    at_two = torch.load(out / "checkpoint.pt", weights_only=False)
    assert at_two["iteration"] == 2
    # What a run killed after the checkpoint leaves: a logged iteration past it, torn line.
    with (out / "metrics.jsonl").open("a") as f:
        f.write(json.dumps({"iteration": 3, "samples": 384, "wall_s": 99.0}) + '\n{"iter')

    with pytest.raises(SystemExit, match="seed 1 -> 2"):
        script.main(small + ["--iterations", "3", "--resume", "--seed", "2"])
    with pytest.raises(SystemExit, match="at iteration 2, past --iterations 1"):
        script.main(small + ["--iterations", "1", "--resume"])
    with pytest.raises(SystemExit, match="nothing to resume"):
        script.main(small[2:] + ["--out", str(tmp_path / "none"), "--resume"])
    with pytest.raises(SystemExit, match="holds an earlier run's checkpoint"):
        script.main(small + ["--iterations", "2"])

    # Another spelling of the same directory is the same run.
    relative = ["--out", str(Path("..") / out.name)]
    monkeypatch.chdir(out)
    assert script.main(relative + small[2:] + ["--iterations", "3", "--resume"]) == 0
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows] == [1, 2, 3]
    assert [r["samples"] for r in rows] == [128, 256, 384]
    assert rows[2]["wall_s"] > rows[1]["wall_s"] and rows[2]["wall_s"] < 99.0
    at_three = torch.load(out / "checkpoint.pt", weights_only=False)
    assert at_three["iteration"] == 3
    # The third update started from the second's networks and Adam moments, so it moved
    # them on from there (the std is the first parameter an update changes).
    assert at_three["optimizer"]["state"][0]["step"] == at_two["optimizer"]["state"][0]["step"] + 5 * 4


def test_a_run_killed_after_its_last_update_finishes_on_resume(tmp_path):
    """The final checkpoint comes before the export: resuming at the budget exports,
    checks and referees without training, its wall-clock the run's own."""
    script = load_script()
    out = tmp_path / "run"
    small = ["--out", str(out), "--num-envs", "16", "--steps-per-env", "8", "--iterations", "1",
             "--eval-episodes", "1", "--parity-envs", "8", "--parity-steps", "20"]  # fmt: skip
    assert script.main(small) == 0
    (out / "policy.blob").unlink()
    before = json.loads((out / "summary.json").read_text())
    assert script.main(small + ["--resume"]) == 0
    assert (out / "policy.blob").exists()
    after = json.loads((out / "summary.json").read_text())
    assert after["iterations"] == 1 and abs(after["wall_s"] - before["wall_s"]) < 1.0
    rows = (out / "metrics.jsonl").read_text().splitlines()
    assert len(rows) == 1


def test_a_folded_run_with_a_pass_decay_exports_a_folded_blob(tmp_path):
    """--fold-mirror trains on folded observations and the blob records the fold (the
    controller folds only what the blob says), equal to PyTorch's actor on a folded rollout.
    --pass-decay lowers the pass weight between rollouts as host-trainer's [pass_decay]."""
    script = load_script()
    out = tmp_path / "run"
    argv = ["--out", str(out), "--num-envs", "16", "--steps-per-env", "8", "--iterations", "3",
            "--eval-episodes", "1", "--parity-envs", "32", "--parity-steps", "50",
            "--fold-mirror", "--pass-decay", "0", "1", "2", "--reward-weight", "crash=1"]  # fmt: skip
    assert script.main(argv) == 0
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["pass_weight"] for r in rows] == [1.0, 1.0, 0.0]
    args = script.parse_args(argv)
    assert script.rewards_at(args, 0) == {"crash": 1.0, "pass": 1.0}
    assert script.rewards_at(args, 5) == {"crash": 1.0, "pass": 0.0}
    summary = json.loads((out / "summary.json").read_text())
    assert summary["parity_max_abs_err"] <= 1e-5
    import overtake

    assert overtake.Policy(out / "policy.blob").fold_mirror


def test_the_schedules_are_host_trainers():
    """The σ ceiling, the pass weight and the KL target fall as host-trainer's schedules do
    (host-trainer/tests/config.rs holds the same numbers): constant until FROM, linear to
    FINAL at TO, constant after; exactly the start value before the fall."""
    script = load_script()
    args = script.parse_args([
        "--out", "unused", "--max-std", "1.0", "--max-std-decay", "0.4", "100", "400",
        "--pass-decay", "0.25", "100", "400", "--desired-kl", "0.01",
        "--desired-kl-decay", "0.001", "100", "400", "--reward-weight", "crash=1",
    ])  # fmt: skip
    for it, std, pass_w, kl in [
        (0, 1.0, 1.0, 0.01),
        (100, 1.0, 1.0, 0.01),
        (250, 0.7, 0.625, 0.0055),
        (400, 0.4, 0.25, 0.001),
        (10_000, 0.4, 0.25, 0.001),
    ]:
        assert script.max_std_at(args, it) == pytest.approx(std)
        assert script.rewards_at(args, it) == pytest.approx({"crash": 1.0, "pass": pass_w})
        assert script.desired_kl_at(args, 0.01, it) == pytest.approx(kl)
    assert script.desired_kl_at(args, 0.01, 100) == 0.01


@pytest.mark.parametrize(
    "extra, text",
    [
        (["--row", "G", "--fold-mirror"], "not row G"),
        (["--max-std-decay", "0.1", "1", "4"], "lowers a value that is not given"),
        (["--max-std", "1.0", "--max-std-decay", "1.5", "1", "4"], "FINAL must be in"),
        (["--pass-decay", "-1", "1", "4"], "FINAL must be in"),
        (["--pass-decay", "0", "4", "4"], "FROM < TO"),
        (["--desired-kl", "0.01", "--desired-kl-decay", "0", "1", "4"], "FINAL must be in"),
        (["--desired-kl", "0.01", "--desired-kl-decay", "0.001", "1.5", "4"], "whole numbers"),
    ],
)
def test_bad_schedules_are_refused_before_anything_runs(tmp_path, extra, text):
    script = load_script()
    with pytest.raises(SystemExit, match=text):
        script.main(["--out", str(tmp_path / "run"), *extra])
    assert not (tmp_path / "run").exists()
