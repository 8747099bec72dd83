#!/usr/bin/env python3
"""Lower bound on the figure-8 lap time: the time-optimal lap of a point mass.

A quadrotor's centre of mass accelerates by (collective thrust)/m along its body z, minus
gravity. Whatever its attitude dynamics, its trajectory is therefore one of a point mass
whose acceleration a satisfies |a + g·e_z| <= (T/W)·g. The fastest periodic lap of that
point mass through the six gate openings, in racing order, bounds every drone's lap from
below; the rotational dynamics (the same motors also have to turn the vehicle) only add to
it.

The problem is solved by direct multiple shooting with IPOPT (CasADi): per gate-to-gate
segment N intervals of constant acceleration and a free duration; the segment ends on the
gate's plane with |y|, |z| <= the opening's half-size (0.8 m), moving through it
front to back; z >= 0.1 m (the ground crash); the lap is periodic (the end state is the
start state). Gate centres and headings are those of docs/DESIGN.md "Track" (upside-down
frames have y and z negated, which the symmetric opening test does not see).

It is a local solver, so each case is solved from several initial guesses and the best is
kept; the spread is printed. The thrust-to-weight of the `paper` preset follows from
docs/DESIGN.md "Presets": rpm_max = 14468.429·1.8, half of kf·rpm² per propeller, mass 0.027 kg.

    python3 -m pip install casadi numpy
    python3 tools/min_lap_time.py                      # the paper preset, a reserve sweep
    python3 tools/min_lap_time.py --tw 1.618 --half 0.8 0.6
"""

import argparse
import sys

try:
    import casadi as ca
    import numpy as np
except ImportError:
    sys.exit("min_lap_time needs casadi and numpy: python3 -m pip install casadi numpy")

GRAVITY_MPS2 = 9.81
KF_N_PER_RPM2 = 3.16e-10
MASS_KG = 0.027
RPM_MAX = 14468.429 * 1.8
PAPER_TW = 4 * 0.5 * KF_N_PER_RPM2 * RPM_MAX**2 / (MASS_KG * GRAVITY_MPS2)

GATES_M = np.array(
    [[0, 0, 1], [10, 5, 1], [10, -5, 1], [0, 0, 1], [-10, 5, 1], [-10, -5, 1]], float
)
HEADINGS_RAD = np.radians([0.0, -39.81, -140.19, 180.0, -140.19, -39.81])
FORWARD = np.stack([np.cos(HEADINGS_RAD), np.sin(HEADINGS_RAD), 0 * HEADINGS_RAD], 1)
LEFT = np.stack([-np.sin(HEADINGS_RAD), np.cos(HEADINGS_RAD), 0 * HEADINGS_RAD], 1)
GROUND_M = 0.1


def at_gate(opti, state, gate, half_m):
    """`state` (position, velocity) is on `gate`'s plane, inside the opening, moving through."""
    rel = state[0:3] - GATES_M[gate]
    opti.subject_to(ca.dot(rel, FORWARD[gate]) == 0)
    opti.subject_to(ca.fabs(ca.dot(rel, LEFT[gate])) <= half_m)
    opti.subject_to(ca.fabs(rel[2]) <= half_m)
    opti.subject_to(ca.dot(state[3:6], FORWARD[gate]) >= 0.5)


def solve(tw, half_m, intervals, cruise_mps, swing_m, flying, laps=1):
    """The time-optimal lap from one initial guess: (lap s, segment times, states) or None.

    `flying`: the lap's start state at g0 is free instead of equal to its end state (a
    single flying lap, the referee's "fastest lap" of an episode, rather than a lap that
    can be repeated). `laps` > 1 with `flying`: that many laps from a free state at g0, the
    last one timed (the earlier laps may set it up)."""
    g = GRAVITY_MPS2
    n_track = len(GATES_M)
    n_gates = n_track * laps
    opti = ca.Opti()
    seg_s = opti.variable(n_gates)
    states, accels = [], []
    for k in range(n_gates):
        x = opti.variable(6, intervals + 1)
        u = opti.variable(3, intervals)  # specific thrust (m/s^2, world)
        states.append(x)
        accels.append(u)
        dt = seg_s[k] / intervals
        for i in range(intervals):
            a = u[:, i] - ca.DM([0, 0, g])
            opti.subject_to(x[0:3, i + 1] == x[0:3, i] + dt * x[3:6, i] + 0.5 * dt**2 * a)
            opti.subject_to(x[3:6, i + 1] == x[3:6, i] + dt * a)
            opti.subject_to(ca.sumsqr(u[:, i]) <= (tw * g) ** 2)
        opti.subject_to(x[2, :] >= GROUND_M)
        opti.subject_to(seg_s[k] >= 0.2)
    for k in range(n_gates):
        end, nxt = states[k][:, intervals], states[(k + 1) % n_gates][:, 0]
        if k + 1 < n_gates or not flying:
            opti.subject_to(end == nxt)
        at_gate(opti, end, (k + 1) % n_track, half_m)
    if flying:
        at_gate(opti, states[0][:, 0], 0, half_m)
    opti.minimize(ca.sum1(seg_s[n_gates - n_track :]))
    for k in range(n_gates):
        a, b = GATES_M[k % n_track], GATES_M[(k + 1) % n_track]
        length = np.linalg.norm(b - a)
        opti.set_initial(seg_s[k], length / cruise_mps)
        for i in range(intervals + 1):
            s = i / intervals
            bulge = swing_m * np.sin(np.pi * s) * np.array([0, 0, 1.0])
            opti.set_initial(states[k][0:3, i], a + (b - a) * s + bulge)
            opti.set_initial(states[k][3:6, i], (b - a) / length * cruise_mps)
        opti.set_initial(accels[k], np.tile([[0], [0], [g]], (1, intervals)))
    opti.solver("ipopt", {"print_time": False}, {"print_level": 0, "max_iter": 5000})
    try:
        sol = opti.solve()
    except RuntimeError:
        return None
    segs = np.array(sol.value(seg_s)).ravel()[n_gates - n_track :]
    xs = np.concatenate(
        [sol.value(states[k])[:, :-1] for k in range(n_gates - n_track, n_gates)], 1
    )
    return segs.sum(), segs, xs


def best_of(tw, half_m, intervals, flying, laps):
    """The best of several initial guesses: (best solution, every lap found, guesses)."""
    guesses = [(c, s) for c in (6.0, 8.0, 10.0) for s in (0.0, 0.4)]
    found = []
    best = None
    for cruise, swing in guesses:
        r = solve(tw, half_m, intervals, cruise, swing, flying, laps)
        if r is None:
            continue
        found.append(r[0])
        if best is None or r[0] < best[0]:
            best = r
    return best, found, len(guesses)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--tw",
        type=float,
        nargs="*",
        help="thrust-to-weight ratios (default: the paper preset at 100, 97, 93 and 90 %%)",
    )
    p.add_argument("--half", type=float, nargs="*", default=[0.8], help="opening half-size (m)")
    p.add_argument("--intervals", type=int, default=40, help="intervals per gate segment")
    p.add_argument(
        "--flying",
        action="store_true",
        help="a single flying lap: the state entering g0 is free (default: a repeatable lap)",
    )
    p.add_argument(
        "--laps",
        type=int,
        default=1,
        help="with --flying: laps flown from the free state, the last one timed",
    )
    args = p.parse_args()
    tws = args.tw or [PAPER_TW * f for f in (1.0, 0.97, 0.93, 0.90)]
    if args.laps > 1 and not args.flying:
        p.error("--laps needs --flying")
    kind = f"flying lap {args.laps} from a free state" if args.flying else "repeatable lap"
    print(f"paper preset thrust-to-weight: {PAPER_TW:.4f}; {kind}")
    print("| T/W | share of paper's | opening half-size (m) | lap (s) | initial guesses solved, laps (s) | speed min-max (m/s) |")
    print("|---|---|---|---|---|---|")
    for tw in tws:
        for half in args.half:
            best, laps, tried = best_of(tw, half, args.intervals, args.flying, args.laps)
            if best is None:
                print(f"| {tw:.3f} | {tw / PAPER_TW:.0%} | {half} | no solution | 0 of {tried} | |")
                continue
            speed = np.linalg.norm(best[2][3:6], axis=0)
            spread = f"{len(laps)} of {tried}, {min(laps):.3f}-{max(laps):.3f}"
            print(
                f"| {tw:.3f} | {tw / PAPER_TW:.0%} | {half} | **{best[0]:.3f}** | {spread} "
                f"| {speed.min():.1f}-{speed.max():.1f} |"
            )


if __name__ == "__main__":
    main()
