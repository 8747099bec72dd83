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

`--rigid-body` also solves the lap of the drone itself: the paper preset's rigid body
(sitl::dynamics: four rotor commands by eq. 3, held over each control interval, RK4 with two
substeps, the attitude turned by the same rotors that lift), started from the point-mass lap
and periodic in all 13 states. Its lap is what a policy could fly on this simulator (up to
the solver's local optimum); the point mass bounds it from below.

    python3 -m pip install casadi numpy
    python3 tools/min_lap_time.py                      # the paper preset, a reserve sweep
    python3 tools/min_lap_time.py --rigid-body --control-s 0.02   # the drone at 50 Hz
    python3 tools/min_lap_time.py --tw 1.618 --half 0.8 0.6

`--compare TRACE` says where a flown lap loses its time: it reads the positions of
`sitl eval --trace TRACE` (every episode, broken at respawns), finds the gate passes and
every complete lap, and prints per gate-to-gate segment the flight's median time beside the
optimal lap's, with where each crosses the gate (left of the gate's +x and above its
centre, m), its speed there, the path length and the height range; then what the
environment's reward pays per second for each line (progress at the paper's 0.5 per m, the
pass term at weights 1, 0.5 and 0), which says whether the reward prefers the faster line.

    cargo run --release -p sitl -- eval --ego policies/stage1.blob --trace t.json
    python3 tools/min_lap_time.py --compare t.json
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
    us = np.concatenate(
        [np.atleast_2d(sol.value(accels[k])) for k in range(n_gates - n_track, n_gates)], 1
    )
    return segs.sum(), segs, xs, us


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


# The rigid body of the `paper` preset (docs/DESIGN.md "Presets", sitl::dynamics): four
# propellers at (±0.028, ±0.028) m, thrust and yaw torque halved, rpm = base·(1 + 0.8·a).
KM_NM_PER_RPM2 = 7.94e-12
THRUST_SCALE = 0.5
INERTIA_KGM2 = np.array([1.4e-5, 1.4e-5, 2.17e-5])
PROPELLERS_M = np.array([[0.028, -0.028], [-0.028, -0.028], [-0.028, 0.028], [0.028, 0.028]])
SPIN_SIGNS = np.array([-1.0, 1.0, -1.0, 1.0])
RPM_BASE = 14468.429


def rigid_body_derivative(x, act, thrust_share):
    """d/dt of the state (position, velocity, quaternion w x y z, body rates) under the
    actions `act` in [-1, 1] (eq. 3), as sitl::dynamics integrates it; `thrust_share` scales
    the rpm range's top (1 = the preset)."""
    rpm = RPM_BASE * (1 + 0.8 * act) * np.sqrt(thrust_share)
    f = THRUST_SCALE * KF_N_PER_RPM2 * rpm**2
    tau = ca.vertcat(
        ca.dot(ca.DM(PROPELLERS_M[:, 1]), f),
        -ca.dot(ca.DM(PROPELLERS_M[:, 0]), f),
        THRUST_SCALE * KM_NM_PER_RPM2 * ca.dot(ca.DM(SPIN_SIGNS), rpm**2),
    )
    v, q, w = x[3:6], x[6:10], x[10:13]
    qw, qx, qy, qz = q[0], q[1], q[2], q[3]
    body_z = ca.vertcat(2 * (qx * qz + qw * qy), 2 * (qy * qz - qw * qx), 1 - 2 * (qx**2 + qy**2))
    accel = body_z * ca.sum1(f) / MASS_KG - ca.DM([0, 0, GRAVITY_MPS2])
    j = ca.DM(INERTIA_KGM2)
    alpha = (tau - ca.cross(w, j * w)) / j
    qdot = 0.5 * ca.vertcat(
        -qx * w[0] - qy * w[1] - qz * w[2],
        qw * w[0] + qy * w[2] - qz * w[1],
        qw * w[1] - qx * w[2] + qz * w[0],
        qw * w[2] + qx * w[1] - qy * w[0],
    )
    return ca.vertcat(v, accel, qdot, alpha)


def rigid_body_step(x, act, h, substeps, thrust_share):
    """RK4 over `h` seconds in `substeps` substeps, the actions held (as the simulator)."""
    k = h / substeps
    for _ in range(substeps):
        k1 = rigid_body_derivative(x, act, thrust_share)
        k2 = rigid_body_derivative(x + 0.5 * k * k1, act, thrust_share)
        k3 = rigid_body_derivative(x + 0.5 * k * k2, act, thrust_share)
        k4 = rigid_body_derivative(x + k * k3, act, thrust_share)
        x = x + k / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


def attitude_for(thrust_dir):
    """The quaternion (w, x, y, z) of the smallest rotation taking e_z to `thrust_dir`."""
    z = np.array([0.0, 0.0, 1.0])
    d = thrust_dir / np.linalg.norm(thrust_dir)
    axis = np.cross(z, d)
    c = float(np.dot(z, d))
    q = np.array([1 + c, *axis])
    return q / np.linalg.norm(q)


def solve_rigid_body(point_mass, control_s, substeps, thrust_share, min_control_s):
    """The time-optimal repeatable lap of the `paper` rigid body (rotor commands held over
    intervals of about `control_s`, at least `min_control_s`), started from the point-mass
    solution: (lap s, segment times, states, actions) or None."""
    _, segs_pm, xs_pm, _ = point_mass
    n_track = len(GATES_M)
    pm_intervals = xs_pm.shape[1] // n_track
    opti = ca.Opti()
    seg_s = opti.variable(n_track)
    states, actions, counts = [], [], []
    sx, su, sh = ca.SX.sym("x", 13), ca.SX.sym("u", 4), ca.SX.sym("h")
    step = ca.Function("step", [sx, su, sh], [rigid_body_step(sx, su, sh, substeps, thrust_share)])
    for k in range(n_track):
        n = max(8, int(round(segs_pm[k] / control_s)))
        counts.append(n)
        x = opti.variable(13, n + 1)
        u = opti.variable(4, n)
        states.append(x)
        actions.append(u)
        dt = seg_s[k] / n
        steps = step.map(n)(x[:, :-1], u, ca.repmat(dt, 1, n))
        opti.subject_to(x[:, 1:] == steps)
        opti.subject_to(opti.bounded(-1, ca.vec(u), 1))
        opti.subject_to(x[2, :] >= GROUND_M)
        opti.subject_to(ca.sumsqr(x[6:10, 0]) == 1)
        opti.subject_to(dt >= min_control_s)
    for k in range(n_track):
        end, nxt = states[k][:, -1], states[(k + 1) % n_track][:, 0]
        opti.subject_to(end == nxt)
        at_gate(opti, end[0:6], (k + 1) % n_track, 0.8)
    opti.minimize(ca.sum1(seg_s))
    # Initial guess: the point mass's path and speeds, the attitude that points the thrust
    # where the point mass accelerates, a collective that gives that acceleration.
    for k in range(n_track):
        opti.set_initial(seg_s[k], segs_pm[k])
        block = xs_pm[:, k * pm_intervals : (k + 1) * pm_intervals + 1]
        if block.shape[1] < pm_intervals + 1:
            block = np.concatenate([block, xs_pm[:, :1]], 1)
        n = counts[k]
        src = np.linspace(0, 1, block.shape[1])
        dst = np.linspace(0, 1, n + 1)
        pv = np.stack([np.interp(dst, src, block[r]) for r in range(6)])
        dt = segs_pm[k] / n
        acc = np.gradient(pv[3:6], dt, axis=1) + np.array([[0], [0], [GRAVITY_MPS2]])
        quats = np.stack([attitude_for(acc[:, i]) for i in range(n + 1)], 1)
        opti.set_initial(states[k][0:6, :], pv)
        opti.set_initial(states[k][6:10, :], quats)
        opti.set_initial(states[k][10:13, :], 0)
        thrust_n = MASS_KG * np.linalg.norm(acc[:, :n], axis=0) / 4
        rpm = np.sqrt(thrust_n / (THRUST_SCALE * KF_N_PER_RPM2 * thrust_share))
        opti.set_initial(actions[k], np.tile(np.clip((rpm / RPM_BASE - 1) / 0.8, -1, 1), (4, 1)))
    opti.solver(
        "ipopt",
        {"print_time": False},
        # Exact Hessians wander off (the rates' dynamics are stiff: 1.4e-5 kg·m² of
        # inertia); quasi-Newton with an adaptive barrier converges from the point mass.
        {
            "print_level": 0,
            "max_iter": 5000,
            "mu_strategy": "adaptive",
            "hessian_approximation": "limited-memory",
            "acceptable_tol": 1e-5,
            "acceptable_constr_viol_tol": 1e-6,
            "acceptable_iter": 10,
        },
    )
    try:
        sol = opti.solve()
    except RuntimeError:
        return None
    segs = np.array(sol.value(seg_s)).ravel()
    xs = np.concatenate([sol.value(states[k])[:, :-1] for k in range(n_track)], 1)
    us = np.concatenate([sol.value(actions[k]) for k in range(n_track)], 1)
    return segs.sum(), segs, xs, us, [segs[k] / counts[k] for k in range(n_track)]


def rigid_body_report(intervals, control_s):
    """Prints the point-mass and the rigid-body repeatable laps of the paper preset."""
    point_mass, _, _ = best_of(PAPER_TW, 0.8, intervals, False, 1)
    if point_mass is None:
        sys.exit("the point-mass lap did not solve")
    print(f"point mass, T/W {PAPER_TW:.3f}: repeatable lap {point_mass[0]:.3f} s")
    r = solve_rigid_body(point_mass, control_s, 2, 1.0, 0.0)
    if r is None:
        sys.exit("the rigid-body lap did not converge from the point-mass start")
    lap, segs, xs, us, held = r
    speed = np.linalg.norm(xs[3:6], axis=0)
    print(
        f"rigid body, rotor commands held {min(held) * 1e3:.0f}-{max(held) * 1e3:.0f} ms: "
        f"repeatable lap {lap:.3f} s ({lap / point_mass[0]:.3f} x the point mass); segments "
        f"{', '.join(f'{t:.3f}' for t in segs)} s; speed {speed.min():.1f}-{speed.max():.1f} m/s; "
        f"commands at +1: {(us >= 0.999).mean():.0%}"
    )


def gate_crossing(p0, p1, gate, half_m):
    """Where the step p0 -> p1 crosses ``gate``'s plane front to back inside the opening:
    (fraction of the step, left m, up m), else None."""
    a, b = (p0 - GATES_M[gate]) @ FORWARD[gate], (p1 - GATES_M[gate]) @ FORWARD[gate]
    if not a < 0 <= b:
        return None
    f = -a / (b - a)
    rel = p0 + f * (p1 - p0) - GATES_M[gate]
    left, up = rel @ LEFT[gate], rel[2]
    if abs(left) > half_m or abs(up) > half_m:
        return None
    return f, left, up


def flown_passes(positions, respawns, dt):
    """Gate passes of one traced episode: lists of (time s, gate, left, up, speed, step),
    one list per stretch between respawns. After a (re)spawn the target is unknown, so the
    first pass of any gate starts the count."""
    stretches, bounds = [], [0, *sorted(respawns), len(positions)]
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        passes, target = [], None
        for i in range(lo + 1, hi):
            for gate in range(len(GATES_M)) if target is None else [target]:
                c = gate_crossing(positions[i - 1], positions[i], gate, 0.8)
                if c is None:
                    continue
                f, left, up = c
                speed = np.linalg.norm(positions[i] - positions[i - 1]) / dt
                passes.append(((i - 1 + f) * dt, gate, left, up, speed, i))
                target = (gate + 1) % len(GATES_M)
                break
        stretches.append(passes)
    return stretches


def sampled_lap(segs, xs, dt, laps):
    """The solved lap's positions every ``dt`` s over ``laps`` repeats (cubic Hermite
    between the solver's nodes, which hold position and velocity)."""
    intervals = xs.shape[1] // len(segs)
    times = np.concatenate([np.cumsum(np.r_[0.0, segs])[k] + np.arange(intervals) * segs[k] / intervals
                            for k in range(len(segs))] + [[segs.sum()]])  # fmt: skip
    nodes = np.concatenate([xs, xs[:, :1]], 1)
    out = []
    for t in np.arange(0.0, laps * segs.sum(), dt):
        t %= segs.sum()
        j = min(np.searchsorted(times, t, "right") - 1, len(times) - 2)
        h = times[j + 1] - times[j]
        u = (t - times[j]) / h
        p0, p1, v0, v1 = nodes[:3, j], nodes[:3, j + 1], nodes[3:, j], nodes[3:, j + 1]
        out.append(
            (2 * u**3 - 3 * u**2 + 1) * p0 + (u**3 - 2 * u**2 + u) * h * v0
            + (-2 * u**3 + 3 * u**2) * p1 + (u**3 - u**2) * h * v1
        )  # fmt: skip
    return np.array(out)


def reward_rates(positions, dt, half_m):
    """The environment's progress and pass terms over a flight that starts on g0's plane
    (sitl::env reward: progress d_{t-1} - d_t to the gate flown to, per m; pass 1 - |p - g|
    after the passing step), unweighted and per simulated second: (progress, pass, passes)."""
    target, progress, passed, n = 1, 0.0, 0.0, 0
    for a, b in zip(positions[:-1], positions[1:]):
        g = GATES_M[target]
        progress += np.linalg.norm(a - g) - np.linalg.norm(b - g)
        if gate_crossing(a, b, target, half_m) is not None:
            passed += 1.0 - np.linalg.norm(b - g)
            n += 1
            target = (target + 1) % len(GATES_M)
    seconds = (len(positions) - 1) * dt
    return progress / seconds, passed / seconds, n


def compare_report(trace_path, intervals):
    """Per segment: the flown laps of a trace (medians) beside the optimal lap."""
    import json

    trace = json.loads(open(trace_path).read())
    n = len(GATES_M)
    segs_flown = [[] for _ in range(n)]
    cross = [[] for _ in range(n)]
    paths = [[] for _ in range(n)]
    heights = [[] for _ in range(n)]
    laps = []
    # The longest stretch that starts at g0 (most passes, the first of equals), priced below.
    priced = None
    for ep in trace["episodes"]:
        dt = ep["dt_s"]
        pos = np.asarray(ep["ego_m"], float)
        for passes in flown_passes(pos, ep.get("respawns") or [], dt):
            for k in range(len(passes) - n):
                if passes[k][1] == 0:
                    laps.append(passes[k + n][0] - passes[k][0])
            for a, b in zip(passes[:-1], passes[1:]):
                g = a[1]
                segs_flown[g].append(b[0] - a[0])
                cross[b[1]].append(b[2:5])
                stretch = pos[a[5] - 1 : b[5] + 1]
                paths[g].append(np.linalg.norm(np.diff(stretch, axis=0), axis=1).sum())
                heights[g].append((stretch[:, 2].min(), stretch[:, 2].max()))
            if passes and passes[0][1] == 0 and len(passes) > n:
                if priced is None or len(passes) > len(priced[1]):
                    priced = (pos, passes)
    if not laps:
        sys.exit(f"{trace_path}: no complete lap (g0 -> g0) in the trace")
    best, _, _ = best_of(PAPER_TW, 0.8, intervals, False, 1)
    if best is None:
        sys.exit("the optimal lap did not solve")
    lap_s, opt_segs, xs, _ = best
    print(
        f"{trace_path}: {len(laps)} laps, best {min(laps):.3f} s, median {np.median(laps):.3f} s; "
        f"optimal (point mass, paper preset) {lap_s:.3f} s"
    )
    print(
        "| segment | flown s (median) | optimal s | ratio | flown crossing left, up (m), speed (m/s) "
        "| optimal crossing | flown path m / optimal | flown height m | optimal height m |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for g in range(n):
        nxt = (g + 1) % n
        seg = xs[:, g * intervals : (g + 1) * intervals + 1] if g + 1 < n else np.concatenate(
            [xs[:, g * intervals :], xs[:, :1]], 1
        )
        end = seg[:, -1]
        rel = end[:3] - GATES_M[nxt]
        opt_path = np.linalg.norm(np.diff(seg[:3], axis=1), axis=0).sum()
        if not segs_flown[g]:
            print(f"| g{g} -> g{nxt} | never flown | {opt_segs[g]:.3f} | | | | | | |")
            continue
        t, c = np.median(segs_flown[g]), np.median(np.array(cross[nxt]), axis=0)
        h = np.array(heights[g])
        print(
            f"| g{g} -> g{nxt} | {t:.3f} | {opt_segs[g]:.3f} | {t / opt_segs[g]:.2f} "
            f"| {c[0]:+.2f}, {c[1]:+.2f}, {c[2]:.1f} "
            f"| {rel @ LEFT[nxt]:+.2f}, {rel[2]:+.2f}, {np.linalg.norm(end[3:6]):.1f} "
            f"| {np.median(paths[g]):.1f} / {opt_path:.1f} "
            f"| {np.median(h[:, 0]):.2f}-{np.median(h[:, 1]):.2f} "
            f"| {seg[2].min():.2f}-{seg[2].max():.2f} |"
        )
    # The figure-8 reflected in x = 0 is itself with its halves swapped (sitl::mirror):
    # segment g and segment g + 3 are mirror images, so the optimum flies them alike.
    half = n // 2
    if n % 2 == 0 and all(segs_flown):
        med = [np.median(s) for s in segs_flown]
        pairs = ", ".join(
            f"g{g}->g{g + 1} {med[g]:.3f} / g{g + half}->g{(g + half + 1) % n} {med[g + half]:.3f} s"
            for g in range(half)
        )
        print(
            f"mirror halves (segment g and g+{half} are reflections of each other): {pairs}; "
            f"the faster of each pair on both halves: {2 * sum(min(med[g], med[g + half]) for g in range(half)):.3f} s"
        )
    # What the reward pays for each line: the optimum's positions at the simulator's rate
    # (its corners lie on the opening's edge, which sampling can miss by a centimetre).
    dt = trace["episodes"][0]["dt_s"]
    opt = reward_rates(sampled_lap(opt_segs, xs, dt, 5), dt, 0.85)
    if priced is not None:
        pos, passes = priced
        prog, pas, _ = reward_rates(pos[passes[0][5] - 1 : passes[-1][5] + 1], dt, 0.8)
        print(
            "reward per simulated second (progress 0.5 per m, as the paper; dt-weighted as "
            "the environment) of the longest stretch from g0 without a respawn:"
        )
        for w in (1.0, 0.5, 0.0):
            # Every term is paid x dt per step: per second, dt x (0.5 m/s of progress + w x pass).
            flown_r, opt_r = (dt * (0.5 * a + w * b) for a, b in ((prog, pas), opt[:2]))
            print(
                f"  pass weight {w}: flown {flown_r:.5f} /s, optimal {opt_r:.5f} /s "
                f"(optimal / flown {opt_r / flown_r:.3f})"
            )


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
    p.add_argument(
        "--rigid-body",
        action="store_true",
        help="also solve the repeatable lap of the paper preset's rigid body (four rotor "
        "commands held over each control interval, the attitude turned by the same motors; "
        "takes tens of minutes), started from the point-mass lap",
    )
    p.add_argument(
        "--control-s",
        type=float,
        default=0.04,
        help="with --rigid-body: the length the rotor commands are held (s; about, the "
        "segment times are free; the simulator's is 0.02)",
    )
    p.add_argument(
        "--compare",
        metavar="TRACE",
        help="where a flown lap loses time: per segment, the laps in TRACE (sitl eval "
        "--trace) beside the optimal lap",
    )
    args = p.parse_args()
    if args.compare:
        compare_report(args.compare, args.intervals)
        return
    if args.rigid_body:
        rigid_body_report(args.intervals, args.control_s)
        return
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
