#!/usr/bin/env python3
"""Checks `sitl race`'s ground-station link and telemetry log with pymavlink, an
independent MAVLink implementation (pip install pymavlink).

    python3 tools/gcs_check.py path/to/sitl [--seconds 5]

Listens on a free UDP port as a ground station would, runs a two-drone race streamed to it
at wall-clock speed (`--realtime`, as a ground station watches one; at full speed a race
outruns a Python receiver and its socket drops datagrams),
and checks: HEARTBEAT at 1 Hz (simulated) from component 1 of each drone with type
QUADROTOR; ATTITUDE, LOCAL_POSITION_NED, GLOBAL_POSITION_INT (around the fixed origin,
consistent with the local position) and SYS_STATUS from each; no frame pymavlink rejects.
Then reads the race's .tlog back and checks the same messages and its timestamps.
Exit status 0 when every check passes; each failure is printed.
"""

import argparse
import math
import os
import socket
import subprocess
import sys
import tempfile
from collections import Counter, defaultdict

from pymavlink import mavutil

ORIGIN_LAT, ORIGIN_LON, ORIGIN_ALT_M = 47.397742, 8.545594, 488.0
WANTED = ["HEARTBEAT", "SYS_STATUS", "ATTITUDE", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"]

failures = []


def check(ok, what):
    if not ok:
        failures.append(what)
        print("FAIL:", what)


def free_port():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def drain(conn, until_exit, proc):
    """All messages until the race process has exited and the socket is quiet."""
    out = []
    quiet = 0
    while True:
        m = conn.recv_match(blocking=True, timeout=0.2)
        if m is None:
            if proc.poll() is not None:
                quiet += 1
                if quiet >= 3:
                    return out
            continue
        quiet = 0
        out.append(m)


def check_stream(msgs, seconds, label):
    by = defaultdict(Counter)
    bad = 0
    for m in msgs:
        t = m.get_type()
        if t == "BAD_DATA":
            bad += 1
            continue
        by[(m.get_srcSystem(), m.get_srcComponent())][t] += 1
    check(bad == 0, f"{label}: {bad} frames pymavlink rejected")
    for sysid in (1, 2):
        c = by.get((sysid, 1), Counter())
        for t in WANTED:
            check(c[t] > 0, f"{label}: no {t} from system {sysid} component 1")
        # 1 Hz of simulated time: one at t = 0 and one per second after.
        check(abs(c["HEARTBEAT"] - seconds) <= 1,
              f"{label}: {c['HEARTBEAT']} heartbeats from system {sysid} in {seconds} s")
    for m in msgs:
        t = m.get_type()
        if t == "HEARTBEAT":
            check(m.type == mavutil.mavlink.MAV_TYPE_QUADROTOR, f"{label}: heartbeat type {m.type}")
            check(m.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED, f"{label}: not armed")
    # GLOBAL_POSITION_INT agrees with LOCAL_POSITION_NED of the same system and time.
    local = {(m.get_srcSystem(), m.time_boot_ms): m for m in msgs if m.get_type() == "LOCAL_POSITION_NED"}
    checked = 0
    for g in (m for m in msgs if m.get_type() == "GLOBAL_POSITION_INT"):
        l = local.get((g.get_srcSystem(), g.time_boot_ms))
        if l is None:
            continue
        lat = ORIGIN_LAT + math.degrees(l.x / 6378137.0)
        lon = ORIGIN_LON + math.degrees(l.y / (6378137.0 * math.cos(math.radians(ORIGIN_LAT))))
        check(abs(g.lat / 1e7 - lat) < 2e-7 and abs(g.lon / 1e7 - lon) < 2e-7,
              f"{label}: lat/lon {g.lat} {g.lon} vs local {l.x:.3f} {l.y:.3f}")
        check(abs(g.relative_alt + l.z * 1000.0) <= 1.0, f"{label}: relative_alt {g.relative_alt} vs z {l.z}")
        check(abs(g.alt - (ORIGIN_ALT_M * 1000.0 + g.relative_alt)) <= 1.0, f"{label}: alt {g.alt}")
        check(abs(g.vx / 100.0 - l.vx) <= 0.006, f"{label}: vx {g.vx} vs {l.vx}")
        checked += 1
    check(checked > 10, f"{label}: only {checked} GLOBAL_POSITION_INT matched a local position")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sitl", help="the sitl binary")
    ap.add_argument("--seconds", type=int, default=5)
    args = ap.parse_args()

    port = free_port()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", dialect="common")
    tmp = tempfile.mkdtemp(prefix="gcs-check-")
    tlog = os.path.join(tmp, "race.tlog")
    cmd = [args.sitl, "race", "--ego", "baseline:8:0.3", "--opponent", "baseline",
           "--episodes", "1", "--seconds", str(args.seconds), "--gcs", f"127.0.0.1:{port}",
           "--gcs-rate-hz", "25", "--tlog", tlog, "--no-plot", "--in-process", "--realtime"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    msgs = drain(gcs, True, proc)
    err = proc.stderr.read().decode()
    check(proc.returncode == 0, f"sitl race exited {proc.returncode}: {err}")
    print(f"ground station: {len(msgs)} messages: {dict(Counter(m.get_type() for m in msgs))}")
    check_stream(msgs, args.seconds, "udp")

    log = mavutil.mavlogfile(tlog)
    logged = []
    while True:
        m = log.recv_match()
        if m is None:
            break
        logged.append(m)
    print(f"tlog: {len(logged)} messages")
    check_stream(logged, args.seconds, "tlog")
    stamps = [m._timestamp for m in logged]
    check(all(a <= b for a, b in zip(stamps, stamps[1:])), "tlog timestamps go backwards")
    span = stamps[-1] - stamps[0] if stamps else 0
    check(abs(span - (args.seconds - 0.04)) < 0.1, f"tlog spans {span:.3f} s, race {args.seconds} s")

    if failures:
        print(f"{len(failures)} checks failed")
        return 1
    print("all ground-station checks passed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
