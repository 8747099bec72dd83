#!/usr/bin/env python3
"""Where flights fail: the flights of a `sitl eval --trace` file grouped by the ego's start
point, with how many ended within the first seconds and how many of those ended with the ego
on the ground. A race restarts both drones at the stage-2 spawn of a random gate after any
crash, so every crash of either drone is another start from rest; a policy that fails a start
under a perturbation loses gates there whoever crashed before.

The trace records the steps where flights restarted, not who crashed or why; "ego on the
ground" is the ego below GROUND_M at the last step of the flight (a ground crash of the ego;
a gate-frame crash or a collision leaves it in the air). A flight that reaches the end of its
episode is not counted as ended.

    target/release/sitl eval --ego policies/stage2.blob --opponent policies/stage1.blob \\
        --jitter --seed 2000 --episodes 100 --perturb motor-tau-ms=20 --trace /tmp/lag.json
    python3 tools/flight_starts.py /tmp/lag.json
"""

import argparse
import json
import sys

GROUND_M = 0.15
CLUSTER_M = 0.5


def flights(trace):
    """(start position of the ego, steps flown, ended by a restart, ego z at the last step,
    control step in s) for every flight of every episode."""
    for e in trace["episodes"]:
        n = len(e["ego_m"])
        starts = [0] + list(e["respawns"])
        ends = list(e["respawns"]) + [n]
        for s, r in zip(starts, ends):
            if s >= n:
                continue
            yield e["ego_m"][s], r - s, r < n, e["ego_m"][r - 1][2], e["dt_s"]


def table(trace, early_s):
    """Rows keyed by start point: starts within CLUSTER_M of a row's first start share it
    (the jitter moves a start by a few centimetres)."""
    by_start = {}
    for start, steps, ended, last_z, dt in flights(trace):
        key = next((k for k in by_start if abs(k[0] - start[0]) < CLUSTER_M
                    and abs(k[1] - start[1]) < CLUSTER_M), (start[0], start[1]))
        row = by_start.setdefault(key, [0, 0, 0])
        row[0] += 1
        if ended and steps * dt < early_s:
            row[1] += 1
            if last_z < GROUND_M:
                row[2] += 1
    return by_start


def metres(v):
    """`v` to a decimetre, without a sign on zero."""
    text = f"{v:.1f}"
    return "0.0" if text == "-0.0" else text


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("trace", help="a `sitl eval --trace` JSON file")
    p.add_argument("--early-s", type=float, default=1.2,
                   help="a flight that ends before this many seconds failed its start (default 1.2)")
    a = p.parse_args()
    try:
        with open(a.trace) as f:
            trace = json.load(f)
        rows = table(trace, a.early_s)
    except (OSError, ValueError, KeyError, IndexError, TypeError) as e:
        sys.exit(f"{a.trace}: not a readable `sitl eval --trace` file ({e!r})")
    if not rows:
        sys.exit(f"{a.trace}: no flights")
    print(f"| ego's start (x, y) m | flights | ended < {a.early_s:g} s | of those, ego on the ground |")
    print("|---|---|---|---|")
    total = [0, 0, 0]
    for key in sorted(rows):
        n, early, ground = rows[key]
        total = [t + v for t, v in zip(total, (n, early, ground))]
        print(f"| ({metres(key[0])}, {metres(key[1])}) | {n} | {early} ({early / n:.0%}) | {ground} |")
    print(f"| all | {total[0]} | {total[1]} ({total[1] / total[0]:.0%}) | {total[2]} |")


if __name__ == "__main__":
    main()
