#!/usr/bin/env python3
"""The race replay checked as a person would see it (CI: .ci/run).

1. `sitl race` writes a replay page (--replay) and the same episodes as JSON (--trace).
2. The page's data, decoded here with Python's own base64 and struct, must give back the
   trace's positions, attitudes, speeds and leads to 1e-6 (they are the same f32 values),
   and the same events.
3. Headless Chromium renders the page's probe view (#probe=1: the 3-D view alone, from
   above) at a chosen moment. The pixels at the recorded poses must show what the page
   should draw there: each drone's colour at its position, its white nose and its four
   rotors where its recorded attitude puts them (viewer.js NOSE, ROTOR_M), the gates'
   colour at each gate's centre and at both ends of its top bar (the gate's heading), the
   background where nothing flies. The top view's framing is recomputed here from its
   documented rule (viewer.js FRAMING), not read from the page.
4. The default view (chase camera, panels, timeline) loads without a script error.

    python3 tools/replay/check.py --sitl target/release/sitl [--chromium /usr/bin/chromium]
"""

import argparse
import base64
import json
import math
import os
import re
import shutil
import struct
import subprocess
import sys
import tempfile

STATE_FLOATS = 8
MARGIN_M = 2.0  # viewer.js FRAMING.margin_m
COLORS = {  # viewer.js COLORS, as sRGB bytes
    "background": (0x14, 0x17, 0x1C),
    "gate": (0xF2, 0xF2, 0xF2),
    "ego": (0xFF, 0x5A, 0x1F),
    "opponent": (0x2F, 0x8C, 0xFF),
    "nose": (0xFF, 0xFF, 0xFF),
    "rotor": (0x3A, 0x3F, 0x48),
}
NOSE_M = (0.12, 0.0, 0.03)  # viewer.js NOSE.at_m, body frame
TRAIL_S = 1.5  # viewer.js TRAIL_S: the seconds of path drawn behind each drone
TRAIL_CLEAR_M = 0.5  # a drone's body (0.16 m) and rotors clear of the other's trail line
ROTOR_M = 0.177  # viewer.js ROTOR_M
ROTOR_Z_M = 0.015
GATE_BAR_M = 0.1  # viewer.js GATE_BAR_M
TOLERANCE = 8  # per channel, for the renderer's colour-space round trip
WIDTH, HEIGHT = 900, 700
CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--hide-scrollbars", "--virtual-time-budget=4000",
]


def replay_data(page):
    m = re.search(r'<script type="application/json" id="replay-data">(.*?)</script>', page, re.S)
    if not m:
        sys.exit("no replay data in the page")
    return json.loads(m.group(1))


def f32s(text):
    raw = base64.b64decode(text)
    return struct.unpack("<%df" % (len(raw) // 4), raw)


def check_round_trip(data, traces):
    assert data["format"] == "overtake-replay/1", data["format"]
    assert len(data["episodes"]) == len(traces["episodes"]), "episode count"
    worst = 0.0
    for i, (e, t) in enumerate(zip(data["episodes"], traces["episodes"])):
        assert e["steps"] == len(t["ego_m"]), (i, "steps")
        for key in ("ego", "opponent"):
            s = f32s(e[key])
            assert len(s) == STATE_FLOATS * e["steps"], (i, key, "length")
            for k in range(e["steps"]):
                row = s[STATE_FLOATS * k:STATE_FLOATS * (k + 1)]
                want = t[f"{key}_m"][k] + t[f"{key}_attitude"][k] + [t[f"{key}_speed_mps"][k]]
                worst = max(worst, max(abs(a - b) for a, b in zip(row, want)))
        lead = f32s(e["lead_m"])
        assert len(lead) == e["steps"] == len(t["lead_m"]), (i, "lead length")
        for a, b in zip(lead, t["lead_m"]):
            assert (b is None and math.isnan(a)) or a == b, (i, a, b)
        for key in ("respawns", "overtakes", "events"):
            assert e[key] == t[key], (i, key)
    # The trace's JSON writes each f32 in full, so the page must give back the same values.
    assert worst == 0.0, f"the replay moves a recorded value by {worst}"
    print(f"round trip: {len(traces['episodes'])} episodes, every value exact (to 1e-6 m asked)")


def framing(gates, width, height):
    xs = [g["center_m"][0] for g in gates]
    ys = [g["center_m"][1] for g in gates]
    bw = max(xs) - min(xs) + 2 * MARGIN_M
    bh = max(ys) - min(ys) + 2 * MARGIN_M
    scale = min(width / bw, height / bh)
    cx, cy = (max(xs) + min(xs)) / 2, (max(ys) + min(ys)) / 2
    return lambda x, y: (width / 2 + (x - cx) * scale, height / 2 - (y - cy) * scale), scale


def pick_moment(data):
    """The first episode and step where the drones are apart, clear of every gate and clear
    of each other's trail (the viewer draws the last TRAIL_S seconds of each path over the
    scene: a drone that flies the other's line a second behind it sits under that trail)."""
    for episode in range(len(data["episodes"])):
        found = moment_in(data, episode)
        if found is not None:
            return (episode, *found)
    sys.exit("no step with the drones apart, clear of the gates and of each other's trail")


def moment_in(data, episode):
    e = data["episodes"][episode]
    ego, opp = f32s(e["ego"]), f32s(e["opponent"])
    gates = [g["center_m"] for g in data["track"]["gates"]]
    respawns = set(e["respawns"])
    trail_steps = round(TRAIL_S / data["dt_s"]) + 1

    def at(states, j):
        return states[STATE_FLOATS * j:STATE_FLOATS * j + 3]

    for k in range(100, e["steps"] - 1):
        if any(j in respawns for j in range(k - trail_steps, k + 2)):
            continue
        a, b = at(ego, k), at(opp, k)
        if math.dist(a[:2], b[:2]) < 1.0:
            continue
        if not all(math.dist(p[:2], g[:2]) > 1.0 for p in (a, b) for g in gates):
            continue
        trails = range(k - trail_steps, k + 1)
        if all(math.dist(b[:2], at(ego, j)[:2]) > TRAIL_CLEAR_M
               and math.dist(a[:2], at(opp, j)[:2]) > TRAIL_CLEAR_M for j in trails):
            return k, a, b
    return None


def chromium(binary, url, out_dir, *extra):
    profile = tempfile.mkdtemp(dir=out_dir)
    cmd = [binary, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", *extra, url]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    shutil.rmtree(profile, ignore_errors=True)
    return r


def rotate(q, v):
    """v (body frame) in the world frame, q = (w, x, y, z) body to world."""
    w, x, y, z = q
    vx, vy, vz = v
    # v + 2 w (u x v) + 2 u x (u x v), u = (x, y, z)
    cx, cy, cz = y * vz - z * vy, z * vx - x * vz, x * vy - y * vx
    return (vx + 2 * (w * cx + y * cz - z * cy),
            vy + 2 * (w * cy + z * cx - x * cz),
            vz + 2 * (w * cz + x * cy - y * cx))


def add(p, v):
    return tuple(a + b for a, b in zip(p, v))


def pixel_near(img, x, y, color, block=2):
    """Whether the block x block pixels whose centres are nearest (x, y) have `color`
    (within TOLERANCE). block 2 for a drone's body (0.16 m: 6 px here); block 1 for thin
    parts: a gate's top bar seen from above is 0.06 m (2.25 px), a rotor 0.17 m across,
    the nose 0.07 m."""
    px = img.load()
    x0, y0 = (math.floor(x - 0.5), math.floor(y - 0.5)) if block == 2 else (math.floor(x), math.floor(y))
    seen = []
    for dy in range(block):
        for dx in range(block):
            p = px[x0 + dx, y0 + dy][:3]
            seen.append(p)
            if any(abs(a - b) > TOLERANCE for a, b in zip(p, color)):
                return False, seen
    return True, seen


def check_pixels(args, page_path, data, out_dir):
    from PIL import Image

    episode, k, ego, opp = pick_moment(data)
    e0 = data["episodes"][episode]
    q = {key: f32s(e0[key])[STATE_FLOATS * k + 3:STATE_FLOATS * k + 7] for key in ("ego", "opponent")}
    t = repr((k + 1) * data["dt_s"])
    shot = os.path.join(out_dir, "probe.png")
    url = f"file://{os.path.abspath(page_path)}#probe=1&episode={episode}&t={t}"
    r = chromium(args.chromium, url, out_dir, f"--window-size={WIDTH},{HEIGHT}", f"--screenshot={shot}")
    if not os.path.exists(shot):
        sys.exit(f"chromium wrote no screenshot:\n{r.stderr[-2000:]}")
    img = Image.open(shot).convert("RGB")
    assert img.size == (WIDTH, HEIGHT), img.size
    to_px, scale = framing(data["track"]["gates"], WIDTH, HEIGHT)
    failures = []
    probes = []  # (what, colour, world point, block)
    for key, p in (("ego", ego), ("opponent", opp)):
        probes.append((key, key, p, 2))
        probes.append((f"{key}'s nose", "nose", add(p, rotate(q[key], NOSE_M)), 1))
        for sx in (1, -1):
            for sy in (1, -1):
                r = rotate(q[key], (sx * ROTOR_M, sy * ROTOR_M, ROTOR_Z_M))
                probes.append((f"{key}'s rotor ({sx:+d}, {sy:+d})", "rotor", add(p, r), 1))
    h = data["track"]["opening_half_size_m"]
    for i, g in enumerate(data["track"]["gates"]):
        probes.append((f"g{i} centre", "gate", g["center_m"], 1))
        for side in (1, -1):  # the top bar's ends: the gate's heading
            end = rotate(g["frame"], (0.0, side * (h + GATE_BAR_M / 2), 0.0))
            probes.append((f"g{i} bar end {side:+d}", "gate", add(g["center_m"], end), 1))
    for what, color, p, block in probes:
        ok, seen = pixel_near(img, *to_px(p[0], p[1]), COLORS[color], block)
        if not ok:
            failures.append(f"{what} at {[round(c, 3) for c in p[:2]]} -> pixel {to_px(p[0], p[1])}: saw {seen}")
    # Nothing is drawn above or below the figure-8's crossing, 1.5 m beyond the gates.
    ys = [g["center_m"][1] for g in data["track"]["gates"]]
    xs = [g["center_m"][0] for g in data["track"]["gates"]]
    cx = (max(xs) + min(xs)) / 2 + 0.5
    for y in (max(ys) + 1.5, min(ys) - 1.5):
        ok, seen = pixel_near(img, *to_px(cx, y), COLORS["background"])
        if not ok:
            failures.append(f"background at ({cx}, {y}): saw {seen}")
    # The drones' colours are their own: the ego's is not at the opponent's place.
    if pixel_near(img, *to_px(opp[0], opp[1]), COLORS["ego"])[0]:
        failures.append("the ego's colour at the opponent's position")
    if failures:
        sys.exit("the rendered replay does not show the recorded positions:\n" + "\n".join(failures))
    print(f"pixels: episode {episode}, step {k} (t = {float(t):.2f} s), {scale:.1f} px/m: {len(probes)} probes (both "
          f"drones' bodies, noses and rotors by their recorded attitudes, "
          f"{len(data['track']['gates'])} gates by centre and heading), background clear")


def check_loads(args, page_path, out_dir):
    url = f"file://{os.path.abspath(page_path)}#t=overtake"
    r = chromium(args.chromium, url, out_dir, "--window-size=1280,720", "--dump-dom")
    body = re.search(r"<body([^>]*)>", r.stdout)
    attrs = body.group(1) if body else ""
    if 'data-error="' in attrs:
        sys.exit(f"the replay page raised: {attrs}")
    if 'data-ready="1"' not in attrs:
        sys.exit(f"the replay page did not draw its first frame:\n{r.stdout[:2000]}\n{r.stderr[-2000:]}")
    print("the default view (chase camera, panels, timeline) drew without a script error")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sitl", default="target/release/sitl")
    ap.add_argument("--chromium", default=shutil.which("chromium") or "/usr/bin/chromium")
    ap.add_argument("--keep", help="keep the files in this directory")
    args = ap.parse_args()
    args.sitl = os.path.abspath(args.sitl)
    out_dir = args.keep or tempfile.mkdtemp()
    os.makedirs(out_dir, exist_ok=True)
    page, trace = os.path.join(out_dir, "race.html"), os.path.join(out_dir, "trace.json")
    subprocess.run([args.sitl, "race", "--in-process", "--episodes", "2", "--seconds", "12",
                    "--gcs", "none", "--no-tlog", "--no-plot", "--replay", page, "--trace", trace],
                   check=True, cwd=out_dir)
    data = replay_data(open(page, encoding="utf-8").read())
    check_round_trip(data, json.load(open(trace)))
    check_pixels(args, page, data, out_dir)
    check_loads(args, page, out_dir)
    if not args.keep:
        shutil.rmtree(out_dir, ignore_errors=True)


if __name__ == "__main__":
    main()
