#!/usr/bin/env python3
"""Head-to-head race table (docs/RESULTS.md "Racing stage1.blob"): every EGO=OPPONENT pair
raced by the referee (`sitl eval --ego E --opponent O`, the paper's stage-2 spawn, 45 s
races, any crash restarting both) on 20 races of seed 0 and 100 races of seed 2000, printed
as a Markdown table: win rate [95 %] (flights); success, crashes /s, best lap, sustained /
all overtakes, and the gates with a sustained overtake.

    python3 tools/head_to_head.py --sitl target/release/sitl \\
        policies/stage2_G.blob=policies/stage1.blob policies/stage1.blob=policies/stage1.blob
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile


def race(sitl, ego, opponent, seed, episodes, jitter):
    with tempfile.TemporaryDirectory() as d:
        out = os.path.join(d, "eval.json")
        cmd = [sitl, "eval", "--ego", ego, "--opponent", opponent, "--seed", str(seed),
               "--episodes", str(episodes), "--json", out]
        if jitter:
            cmd.append("--jitter")
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            sys.exit(f"{' '.join(cmd)} failed:\n{r.stderr}")
        with open(out) as f:
            return json.load(f)


def cell(r):
    ci = r.get("win_rate_ci95") or [float("nan")] * 2
    lap = f"{r['best_lap_s']:.2f} s" if r.get("best_lap_s") else "DNF"
    held = [f"g{g['gate']}" for g in r.get("overtakes_by_gate", []) if g["sustained"] > 0]
    return (f"{r['win_rate']:.3f} [{ci[0]:.3f}, {ci[1]:.3f}] ({r['flights']} flights); "
            f"{r['success_rate']:.3f}, {r['crash_rate']:.3f} /s, {lap}, "
            f"{r['sustained_overtakes']}/{r['overtakes']}"
            + (f" ({', '.join(held)})" if held else ""))


def name(path):
    base = os.path.basename(path)
    return base[:-5] if base.endswith(".blob") else base


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("pairs", nargs="+", metavar="EGO=OPPONENT")
    p.add_argument("--sitl", default="target/release/sitl")
    p.add_argument("--jitter", action="store_true",
                   help="also a column of 100 jittered races (seed 2000)")
    a = p.parse_args()
    cols = [("seed 0, 20 races", 0, 20, False), ("seed 2000, 100 races", 2000, 100, False)]
    if a.jitter:
        cols.append(("seed 2000, 100 races, `--jitter`", 2000, 100, True))
    print("| ego | opponent | " + " | ".join(c[0] for c in cols) + " |")
    print("|---|---|" + "---|" * len(cols))
    for pair in a.pairs:
        if "=" not in pair:
            sys.exit(f"{pair}: expected EGO=OPPONENT")
        ego, opp = pair.split("=", 1)
        cells = [cell(race(a.sitl, ego, opp, s, n, j)) for _, s, n, j in cols]
        print(f"| `{name(ego)}` | `{name(opp)}` | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
