#!/usr/bin/env python3
"""Issue "robust" item 3's bar for time-trial blobs, as one Markdown table: each blob and its
int8 copy (`tools convert --dtype i8`) flown by the referee (`sitl eval`) from jittered
stage-1 starts (`--jitter`: ±5 cm, ±5°, ±0.2 m/s) under the item's conditions, with whether
each bar holds:

- jittered, unperturbed (100 episodes of seed 2000): success >= 0.95, crashes <= 0.05 /s,
  best lap <= 7.8 s; the int8 copy within 0.02 success and 1 % of the f32 best lap;
- one step (20 ms) of action latency, a 20 ms motor lag, and thrust and mass ±10 % (each
  drawn per episode, as the referee's levels are; 20 episodes of seed 0 each): success
  >= 0.9.

With `--opponent`, the blobs are race egos (row G) raced against it from jittered stage-2
starts, and the bar is the item's for G: success >= 0.9 everywhere (no lap or crash bar)
and the int8 copy within 0.02 success and 1 % mean lap.

The int8 copy's lap is compared by the mean lap (over every lap flown): the best of 100
episodes is a minimum that moves by 1-2 % between the f32 and int8 flights of one policy
whose mean laps agree. The four corners of thrust and mass ±10 % are flown too and shown
without a bar: the corner of 10 % less thrust and 10 % more mass leaves 82 % of the
thrust-to-weight ratio the policy learned on.

    python3 tools/robust_bar.py --sitl target/release/sitl --tools target/release/tools \\
        policies/stage1.blob runs/stage1_robust/stage1-robust.blob
    python3 tools/robust_bar.py --opponent policies/stage1.blob policies/stage2.blob
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile

# (label, --perturb spec or None, episodes, seed, success bar or None: shown, not judged)
CONDITIONS = [
    ("jittered", None, 100, 2000, 0.95),
    ("latency 1 step", "latency=1", 20, 0, 0.9),
    ("motor lag 20 ms", "motor-tau-ms=20", 20, 0, 0.9),
    ("thrust and mass ±10 %", "thrust=0.9:1.1,mass=0.9:1.1", 20, 0, 0.9),
    ("corner: thrust 0.9, mass 1.1", "thrust=0.9,mass=1.1", 20, 0, None),
    ("corner: thrust 1.1, mass 0.9", "thrust=1.1,mass=0.9", 20, 0, None),
    ("corner: thrust 0.9, mass 0.9", "thrust=0.9,mass=0.9", 20, 0, None),
    ("corner: thrust 1.1, mass 1.1", "thrust=1.1,mass=1.1", 20, 0, None),
]
MAX_CRASHES_PER_S = 0.05
MAX_BEST_LAP_S = 7.8
INT8_SUCCESS_GAP = 0.02
INT8_LAP_GAP = 0.01
RACE_SUCCESS_FLOOR = 0.9


def run(cmd):
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{r.stderr}")


def evaluate(sitl, blob, opponent, perturb, episodes, seed, workdir):
    out = os.path.join(workdir, "eval.json")
    cmd = [sitl, "eval", "--ego", blob, "--jitter", "--seed", str(seed),
           "--episodes", str(episodes), "--json", out]
    if opponent:
        cmd += ["--opponent", opponent]
    if perturb:
        cmd += ["--perturb", perturb]
    run(cmd)
    with open(out) as f:
        return json.load(f)


def lap(v):
    return f"{v:.2f} s" if v else "DNF"


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("blobs", nargs="+", metavar="BLOB")
    p.add_argument("--sitl", default="target/release/sitl")
    p.add_argument("--tools", default="target/release/tools")
    p.add_argument("--opponent", help="race the blobs (row G) against this opponent")
    a = p.parse_args()
    print("| blob | condition | f32: success, crashes /s, best (mean) lap | "
          "int8: success, crashes /s, best (mean) lap | bar |")
    print("|---|---|---|---|---|")
    failures = 0
    with tempfile.TemporaryDirectory() as d:
        for blob in a.blobs:
            int8 = os.path.join(d, "int8.blob")
            run([a.tools, "convert", "--dtype", "i8", "--in", blob, "--out", int8])
            for label, perturb, episodes, seed, floor in CONDITIONS:
                f, q = (evaluate(a.sitl, b, a.opponent, perturb, episodes, seed, d)
                        for b in (blob, int8))
                if a.opponent and floor is not None:
                    floor = RACE_SUCCESS_FLOOR
                if floor is None:
                    checks = None
                else:
                    checks = [min(f["success_rate"], q["success_rate"]) >= floor]
                if perturb is None and not a.opponent:
                    checks += [
                        f["crash_rate"] <= MAX_CRASHES_PER_S,
                        bool(f["best_lap_s"]) and f["best_lap_s"] <= MAX_BEST_LAP_S,
                    ]
                if perturb is None:
                    checks += [
                        abs(f["success_rate"] - q["success_rate"]) <= INT8_SUCCESS_GAP,
                        bool(f["mean_lap_s"]) and bool(q["mean_lap_s"])
                        and abs(q["mean_lap_s"] / f["mean_lap_s"] - 1) <= INT8_LAP_GAP,
                    ]
                ok = checks is None or all(checks)
                failures += not ok
                verdict = "–" if checks is None else "holds" if ok else "**fails**"
                cells = [f"{r['success_rate']:.3f}, {r['crash_rate']:.3f}, "
                         f"{lap(r['best_lap_s'])} ({lap(r['mean_lap_s'])})" for r in (f, q)]
                print(f"| {os.path.basename(blob)} | {label} ({episodes}, seed {seed}) | "
                      f"{cells[0]} | {cells[1]} | {verdict} |")
    print(f"\n{failures} condition(s) below the bar" if failures else "\nevery bar holds")


if __name__ == "__main__":
    main()
