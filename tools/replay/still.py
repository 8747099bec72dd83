#!/usr/bin/env python3
"""Regenerates docs/replay_overtake.png, the README's still of the race replay: the README's
first command (`sitl race`, the shipped policies, 20 races, seed 0) writes race.html, and
headless Chromium photographs its chase view at the first sustained overtake (else the
first overtake), a moment after the pass.

    cargo build --release -p sitl && python3 tools/replay/still.py [--out docs/replay_overtake.png]
"""

import argparse
import os
import shutil
import subprocess
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from check import chromium  # noqa: E402  (the same headless flags as the CI check)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sitl", default="target/release/sitl")
    ap.add_argument("--chromium", default=shutil.which("chromium") or "/usr/bin/chromium")
    ap.add_argument("--out", default="docs/replay_overtake.png")
    ap.add_argument("--offset", type=float, default=0.3, help="seconds after the pass")
    args = ap.parse_args()
    sitl, out = os.path.abspath(args.sitl), os.path.abspath(args.out)
    work = tempfile.mkdtemp()
    subprocess.run([sitl, "race", "--in-process", "--gcs", "none", "--no-tlog", "--no-plot"],
                   check=True, cwd=work)
    url = f"file://{work}/race.html#t=overtake&offset={args.offset}&view=chase"
    shot = os.path.join(work, "still.png")
    r = chromium(args.chromium, url, work, "--window-size=1280,720", f"--screenshot={shot}")
    if not os.path.exists(shot):
        sys.exit(f"chromium wrote no screenshot:\n{r.stderr[-2000:]}")
    shutil.copyfile(shot, out)
    shutil.rmtree(work, ignore_errors=True)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
