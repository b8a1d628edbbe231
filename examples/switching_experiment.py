"""The switching paper's experiments in simulation: Fig. 8 (switches and error against P) and Table II.

The paper (Hu et al.; ``docs/background.md#references``; sec. 4-5) drives a robot at 0.5 m/s for 30
minutes through an indoor room, a corridor, a big hall and an outdoor square, with three
ceiling cameras, a laser (AMCL) and a depth camera (NDT) as localization components;
a configuration component switches greedily with a changing punishment ``P``. Here:

World (no map needed: each localizer is simulated as a noisy pose source whose error and
reliability depend on the place). Room ``[0, 10] x [0, 8]``; corridor ``[10, 40] x [3, 5]``;
hall ``[40, 60] x [-6, 14]``; outdoor square ``[60, 80] x [-6, 14]``. The robot follows a
fixed loop of waypoints (room, corridor, hall, square, hall, corridor, room; about 210 m)
at 0.5 m/s, again and again. A crowd is in the hall part of the time (an on/off Markov
process, 30 s on / 70 s off on average).

Localizers (errors are 2-D AR(1) processes, time constant ``tau``, with the place's error
scale; every source reports the reliability its own model gives):

* ``laser`` (AMCL, 5 m range): error 6 cm in the room, 15 cm in the hall (twice that
  in a crowd), 20 cm outdoors; in the corridor (featureless, longer than its range) a
  bias grows along the corridor as a random walk (0.2 m/sqrt(s)) and decays with a 5 s
  time constant after it. Reported covariance: the error scale plus half the bias (AMCL
  underestimates its spread). Reliability: eq. (11)-(12).
* ``depth`` (Kinect + NDT): 10 cm in the room, 12 cm in the hall, 0.35 m in the corridor,
  1 m next to a crowd, 1.5 m outdoors (sunlight). Crashes (error state) at random, once
  per 8 minutes on average; the :class:`~dfusion.policies.Supervisor` restarts it after
  3 s (``error -> reset -> ready -> active``), and it is off the candidates meanwhile.
  Reliability: the NDT score is simulated as ``5000 exp(-2.5 |e|)`` times log-normal
  noise (sigma 0.2, AR(1) with coefficient 0.9), and converted by a :class:`~dfusion.reliability.ScoreErrorTable`
  calibrated on a separate 10-minute run (eq. 17-18, "a lookup table").
* ``cam_room``, ``cam_corridor``, ``cam_square``: ceiling cameras (eq. 1-9 of
  :mod:`dfusion.reliability`, ``N = 900`` rows, ``theta = 58`` deg, detector error ``k = 15``
  pixels); the error is ``k D(phi)`` plus 2 cm; outside the field of view a camera
  reports nothing new (its last estimate, reliability 0).

Policies compared on the same recorded data (the paper also "collected the data from all
the components" and applied "different punishment values" afterwards): each single
localizer alone, greedy switching for ``P`` from 0 to 0.4 (Fig. 8), greedy with ``P = 0.15``
(the paper's range), greedy with the ``P`` selected by
:func:`~dfusion.policies.select_punishment` (largest ``P`` with a mean error within 5 % of
the sweep's best; with and without a 1 s blended transition), information fusion of every healthy source with ``R > 0``, and fusion of
those with ``R > 0.6`` (:class:`~dfusion.policies.FusionFloorPolicy`). A *lost
situation* starts when the output error has stayed above 1 m for 1 s and ends when it
has stayed below 0.5 m for 5 s. The chosen configuration runs inside a :class:`~dfusion.FusionNode`
(``report_source`` + ``output`` every step); the *switch delay* is the wall time from the
reports of a step whose reliabilities cause a switch to the node's output carrying the new
source (the paper measured 135 ms for reconnecting an RT-middleware data port).

Time: the paper's 30 minutes at 10 Hz (AMCL's rate), ``dt = 0.1`` s; ``--quick``:
10 minutes at ``dt = 0.2`` s.

    .venv/bin/python examples/switching_experiment.py [--quick] [--out out/switching]
"""
from __future__ import annotations

import argparse
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.signal import lfilter


from dfusion.fusion import FusionNode  # noqa: E402
from dfusion.estimation import Estimate  # noqa: E402
from dfusion.models import ConstantVelocity  # noqa: E402
from dfusion.reliability import camera_reliability, pixel_angle, pixel_footprint  # noqa: E402
from dfusion.reliability import covariance_reliability, reliability_from_error, ScoreErrorTable  # noqa: E402
from dfusion.policies import (
    BlendedTransitionPolicy,
    Component,
    FusionFloorPolicy,
    GreedySwitchingPolicy,
    select_punishment,
    Supervisor,
)

SPEED = 0.5
WAYPOINTS = np.array([
    (2, 2), (8, 2), (8, 6), (2, 6), (2, 4), (10, 4),          # room, to the corridor door
    (40, 4),                                                   # corridor
    (50, 4), (50, 10), (56, 10), (56, -2), (50, -2), (50, 4),  # hall
    (60, 4), (66, 6), (75, 6), (75, 12), (66, 12), (66, 6),    # outdoor square
    (60, 4), (40, 4), (10, 4), (2, 4), (2, 2),                 # back
], dtype=float)
PLACES = ("room", "corridor", "hall", "square")
SOURCES = ("laser", "depth", "cam_room", "cam_corridor", "cam_square")


def place_of(xy: np.ndarray) -> np.ndarray:
    x = xy[:, 0]
    return np.select([x < 10, x < 40, x < 60], [0, 1, 2], 3)


def route(duration: float, dt: float) -> np.ndarray:
    seg = np.diff(WAYPOINTS, axis=0)
    L = np.hypot(seg[:, 0], seg[:, 1])
    cum = np.concatenate([[0.0], np.cumsum(L)])
    s = (SPEED * np.arange(0.0, duration + 1e-9, dt)) % cum[-1]
    i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(L) - 1)
    u = (s - cum[i]) / L[i]
    return WAYPOINTS[i] + u[:, None] * seg[i]


@dataclass
class Camera:
    name: str
    pos: tuple[float, float]
    heading: float       # rad, horizontal direction the camera looks to
    h: float             # height above the robot's marker (m)
    alpha: float         # installation angle from the vertical (rad)
    theta: float = math.radians(58.0)
    N: int = 900
    k: float = 15.0      # detector error (pixels)
    half_width: float = math.radians(38.0)   # horizontal half field angle

    def observe(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """In view, reliability (eq. 9) and error scale ``k D + 2 cm`` for every position."""
        d = xy - np.asarray(self.pos)
        u = np.array([math.cos(self.heading), math.sin(self.heading)])
        along = d @ u
        across = d @ np.array([-u[1], u[0]])
        phi = np.arctan2(along, self.h) - self.alpha
        inside = (np.abs(phi) <= self.theta / 2) & (np.abs(np.arctan2(across, np.maximum(along, 1e-9)))
                                                     <= self.half_width) & (along > 0)
        R = np.where(inside, camera_reliability(np.clip(phi, -self.theta / 2, self.theta / 2), self.alpha,
                                                self.h, self.theta, self.N, self.k), 0.0)
        D = pixel_footprint(np.clip(phi, -self.theta / 2, self.theta / 2), self.alpha, self.h,
                            pixel_angle(self.theta, self.N))
        E = np.where(inside & np.isfinite(D), self.k * np.where(np.isfinite(D), D, 0.0) + 0.02, np.inf)
        return inside & (R > 0), R, E


CAMERAS = [
    Camera("cam_room", (0.5, 7.5), math.atan2(-5.5, 7.5), 2.0, math.radians(40)),
    Camera("cam_corridor", (22.0, 4.0), 0.0, 3.0, math.radians(35)),
    Camera("cam_square", (70.0, 13.5), -math.pi / 2, 5.0, math.radians(35)),
]


def ar1(scale: np.ndarray, tau: float, dt: float, rng) -> np.ndarray:
    """2-D AR(1) error with stationary RMS ``scale`` (per-axis std ``scale / sqrt 2``)."""
    a = math.exp(-dt / tau)
    n = rng.standard_normal((scale.size, 2)) * (scale[:, None] / math.sqrt(2.0)) * math.sqrt(1 - a * a)
    return lfilter([1.0], [1.0, -a], n, axis=0)


def crowd(K: int, dt: float, rng, on: float = 30.0, off: float = 70.0) -> np.ndarray:
    out = np.zeros(K, bool)
    state, k = False, 0
    while k < K:
        n = int(rng.exponential(on if state else off) / dt) + 1
        out[k:k + n] = state
        k += n
        state = not state
    return out


@dataclass
class Recording:
    t: np.ndarray
    truth: np.ndarray
    place: np.ndarray
    est: dict[str, np.ndarray] = field(default_factory=dict)        # (K, 2)
    var: dict[str, np.ndarray] = field(default_factory=dict)        # (K,) per-axis variance reported
    rel: dict[str, np.ndarray] = field(default_factory=dict)        # (K,)
    healthy: dict[str, np.ndarray] = field(default_factory=dict)    # (K,)
    crashes: int = 0
    lifecycle_events: int = 0


def simulate(duration: float, dt: float, seed: int, table: ScoreErrorTable | None) -> tuple[Recording, dict]:
    """Drive and record every localizer. Without ``table``: the calibration run (scores, errors)."""
    rng = np.random.default_rng(seed)
    t = np.round(np.arange(0.0, duration + 1e-9, dt), 9)
    K = t.size
    truth = route(duration, dt)
    place = place_of(truth)
    people = crowd(K, dt, rng) & (place == 2)
    rec = Recording(t, truth, place)

    # ---- laser: AR(1) error + a bias along the corridor while in it + initial convergence
    scale = np.choose(place, [0.06, 0.10, 0.15, 0.20]) * np.where(people, 2.0, 1.0)
    e = ar1(scale, 2.0, dt, rng)
    bias = np.zeros(K)
    b = 0.0
    in_corr = place == 1
    steps = rng.standard_normal(K) * 0.35 * math.sqrt(dt)
    decay = math.exp(-dt / 5.0)
    for k in range(K):
        b = b + steps[k] if in_corr[k] else b * decay
        bias[k] = b
    e[:, 0] += bias
    start = 1.5 * np.exp(-t / 8.0)                      # AMCL converging from a global start
    e[:, 1] += start
    rep = np.sqrt(scale**2 + (0.8 * bias) ** 2 + start**2) \
        * np.exp(lfilter([1], [1, -0.95], rng.normal(0, 0.3 * math.sqrt(1 - 0.95**2), K)))
    rec.est["laser"] = truth + e
    rec.var["laser"] = rep**2 / 2
    rec.rel["laser"] = np.array([covariance_reliability(np.diag([v, v])) for v in rec.var["laser"]])

    # ---- depth camera: NDT score -> lookup table
    dscale = np.choose(place, [0.10, 0.50, 0.12, 1.5])
    dscale = np.where(people, 1.0, dscale)
    e = ar1(dscale, 1.0, dt, rng)
    err = np.hypot(e[:, 0], e[:, 1])
    noise = lfilter([1], [1, -0.9], rng.normal(0.0, 0.2 * math.sqrt(1 - 0.9**2), K))   # correlated in time
    score = 5000.0 * np.exp(-2.5 * err) * np.exp(noise)
    rec.est["depth"] = truth + e
    calib = {"score": score, "error": err}
    if table is not None:
        E = table.error(score)
        rec.rel["depth"] = reliability_from_error(np.maximum(E, 0.0))
        rec.var["depth"] = np.maximum(E, 0.01) ** 2 / 2

    # ---- ceiling cameras: eq. (9), stale estimate outside the view
    for cam in CAMERAS:
        inside, R, E = cam.observe(truth)
        e = ar1(np.where(inside, E, 0.0), 0.3, dt, rng)
        est = truth + e
        # outside the view the camera keeps its last estimate
        idx = np.where(inside, np.arange(K), -1)
        last = np.maximum.accumulate(idx)
        est = np.where((last >= 0)[:, None], est[np.maximum(last, 0)], np.array(cam.pos))
        rec.est[cam.name] = est
        rec.rel[cam.name] = R
        rec.var[cam.name] = np.where(inside, E, 10.0) ** 2 / 2

    # ---- life cycle: the depth camera crashes; the supervisor restarts it after 3 s
    crash_at = set(np.flatnonzero(rng.random(K) < dt / 480.0).tolist())
    crashed = {"depth": False}

    def clear() -> None:
        crashed["depth"] = False

    comps = {s: Component(s, clock=lambda: 0.0) for s in SOURCES}
    comps["depth"].health = lambda: not crashed["depth"]
    comps["depth"].on_reset = clear
    sup = Supervisor(comps.values(), restart_delay=3.0, clock=lambda: 0.0)
    sup.start(0.0)
    for s in SOURCES:
        rec.healthy[s] = np.ones(K, bool)
    dh = rec.healthy["depth"]
    for k in range(K):
        if k in crash_at and comps["depth"].active:
            crashed["depth"] = True
            rec.crashes += 1
        sup.check(t[k])
        c = comps["depth"]
        if c.active:
            c.report(Estimate("depth", t[k], rec.est["depth"][k], np.eye(2)), t[k])
        s = c.source()
        dh[k] = bool(s is not None and s.healthy)
    rec.lifecycle_events = len(sup.events)
    return rec, calib


def sources_at(rec: Recording, k: int) -> list[Estimate]:
    out = []
    for s in SOURCES:
        v = float(rec.var[s][k])
        out.append(Estimate(s, float(rec.t[k]), rec.est[s][k], np.diag([v, v]), float(rec.rel[s][k]),
                                  bool(rec.healthy[s][k])))
    return out


@dataclass
class Result:
    name: str
    err: np.ndarray
    rel: np.ndarray
    switches: int = 0
    delay_us: float = float("nan")
    chosen: list | None = None


def lost_situations(err: np.ndarray, dt: float, enter: float = 1.0, leave: float = 0.5,
                    min_lost: float = 1.0, recover: float = 5.0) -> int:
    """Episodes with the error above ``enter`` m for at least ``min_lost`` s; an episode ends
    once the error has stayed below ``leave`` m for ``recover`` s."""
    n_enter = max(1, int(round(min_lost / dt)))
    n_recover = max(1, int(round(recover / dt)))
    n, lost, above, below = 0, False, 0, 0
    for e in err:
        if not lost:
            above = above + 1 if e > enter else 0
            if above >= n_enter:
                n, lost, below = n + 1, True, 0
        else:
            below = below + 1 if e < leave else 0
            if below >= n_recover:
                lost, above = False, 0
    return n


FUSED = Estimate("fused", 0.0, np.zeros(2), np.eye(2) * 1e6, 0.0)


def replay(rec: Recording, policy, srcs: list[list[Estimate]], name: str) -> Result:
    K = rec.t.size
    err = np.empty(K)
    rel = np.empty(K)
    chosen = []
    for k in range(K):
        out = policy.decide(FUSED, srcs[k])
        err[k] = math.hypot(*(np.asarray(out.mean) - rec.truth[k]))
        rel[k] = out.reliability
        chosen.append(out.name)
    return Result(name, err, rel, len(getattr(policy, "switches", [])), chosen=chosen)


def single(rec: Recording, names: list[str], label: str) -> Result:
    """A localizer alone (cameras: the most reliable camera, each one's last estimate)."""
    if len(names) == 1:
        s = names[0]
        err = np.hypot(*(rec.est[s] - rec.truth).T)
        return Result(label, err, np.where(rec.healthy[s], rec.rel[s], 0.0))
    R = np.stack([rec.rel[s] for s in names], 1)
    best = R.argmax(1)
    est = np.stack([rec.est[s] for s in names], 1)[np.arange(R.shape[0]), best]
    label += f", in view {100 * np.mean(R.max(1) > 0):.0f} % of the time"
    return Result(label, np.hypot(*(est - rec.truth).T), R.max(1))


def run_in_node(rec: Recording, policy) -> Result:
    """The configuration inside a FusionNode; switch delay = reports of a step to its output."""
    node = FusionNode("robot", [], ConstantVelocity(2, 0.1), window=10, prior=(0.0, np.zeros(4), np.eye(4) * 1e6),
                      policy=policy)
    K = rec.t.size
    err = np.empty(K)
    rel = np.empty(K)
    delays = []
    chosen = []
    prev = None
    srcs = [sources_at(rec, k) for k in range(K)]
    for k in range(K):
        t0 = time.perf_counter()
        for s in srcs[k]:
            node.report_source(s)
        out = node.output()
        t1 = time.perf_counter()
        cur = policy.current
        if prev is not None and cur != prev:
            delays.append(t1 - t0)
        prev = cur
        err[k] = math.hypot(out.mean[0] - rec.truth[k, 0], out.mean[1] - rec.truth[k, 1])
        rel[k] = out.reliability
        chosen.append(out.name)
    return Result("greedy in a FusionNode", err, rel, len(policy.switches),
                  float(np.mean(delays) * 1e6) if delays else float("nan"), chosen)


def table_ii(rows: list[Result], rec: Recording) -> str:
    minutes = rec.t[-1] / 60.0
    dist = float(np.sum(np.hypot(*np.diff(rec.truth, axis=0).T)))
    lines = [
        f"Table II (simulated): {minutes:.0f} min, {dist:.0f} m walked, dt = {rec.t[1] - rec.t[0]:.1f} s, "
        f"{rec.crashes} depth-camera crashes restarted by the supervisor",
        "",
        "| configuration | lost situations | mean error [m] | median error [m] | mean reliability | switches | switches/min | switch delay |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        sw = "-" if r.switches is None else f"{r.switches}"
        spm = "-" if r.switches is None else f"{r.switches / minutes:.1f}"
        dl = "-" if not math.isfinite(r.delay_us) else f"{r.delay_us:.0f} us"
        lines.append(f"| {r.name} | {lost_situations(r.err, rec.t[1] - rec.t[0])} | {np.mean(r.err):.3f} | {np.median(r.err):.3f} | "
                     f"{np.mean(r.rel):.3f} | {sw} | {spm} | {dl} |")
    lines.append("| paper, Table II: LRF / depth camera / RTC switching | 19 per 60 min / 15 per 60 min / 1 per 900 min "
                 "| 0.145 / 0.227 / 0.089 | - | 0.875 / 0.812 / 0.913 | - | 3-4 | 135 ms |")
    return "\n".join(lines)


def plot(out: Path, Ps, sw, err, P_sel, rec: Recording, chosen: list[str], minutes: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(14, 4.5))
    ax = axes[0]
    ax.plot(Ps, sw, "C0-o", label="switches")
    ax.set_xlabel("changing punishment P")
    ax.set_ylabel(f"number of switches ({minutes:.0f} min)", color="C0")
    ax2 = ax.twinx()
    ax2.plot(Ps, err, "C3-s", label="mean error")
    ax2.set_ylabel("mean localization error [m]", color="C3")
    ax.axvspan(0.1, 0.17, color="0.9", zorder=0, label="paper's range")
    ax.axvline(P_sel, color="k", ls="--", lw=1)
    ax.set_title(f"Fig. 8 (simulated): selected P = {P_sel:.2f}")
    ax = axes[1]
    n = min(int(round(120.0 / (rec.t[1] - rec.t[0]))) + 1, rec.t.size)
    for s in SOURCES:
        ax.plot(rec.t[:n], np.where(rec.healthy[s][:n], rec.rel[s][:n], 0.0), label=s)
    names = {s: i for i, s in enumerate(SOURCES)}
    c = np.array([names.get(x, -1) for x in chosen[:n]])
    for i, s in enumerate(SOURCES):
        m = c == i
        ax.scatter(rec.t[:n][m], np.full(m.sum(), 1.04), s=4, color=f"C{i}")
    ax.set_ylim(0, 1.08)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("reliability (dots: source in use)")
    ax.set_title("Fig. 11 (simulated): reliabilities, first 2 minutes")
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    fig.savefig(out / "switching_fig8.png", dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="10 minutes at dt = 0.2 s")
    ap.add_argument("--minutes", type=float, default=None)
    ap.add_argument("--dt", type=float, default=None)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("out/switching"))
    a = ap.parse_args(argv)
    minutes = a.minutes or (10.0 if a.quick else 30.0)
    dt = a.dt or (0.2 if a.quick else 0.1)
    t_start = time.perf_counter()
    logging.getLogger("dfusion.policies.lifecycle").setLevel(logging.ERROR)   # crashes are expected here

    # calibration of the depth camera's score table on a separate run (eq. 17-18)
    _, calib = simulate(600.0, 0.5, a.seed + 1000, None)
    table = ScoreErrorTable.from_samples(calib["score"], calib["error"], bins=15)
    rec, _ = simulate(minutes * 60.0, dt, a.seed, table)
    srcs = [sources_at(rec, k) for k in range(rec.t.size)]

    # Fig. 8: sweep P on the recorded data
    Ps = np.round(np.arange(0.0, 0.401, 0.02), 3)
    sweep = [replay(rec, GreedySwitchingPolicy(P), srcs, f"P={P}") for P in Ps]
    sw = [r.switches for r in sweep]
    err = [float(np.mean(r.err)) for r in sweep]
    lost = [lost_situations(r.err, dt) for r in sweep]
    P_sel = select_punishment(Ps, err, tolerance=0.05)   # lost counts are too few to select on
    print("Fig. 8 (simulated): P, switches, mean error [m], lost situations")
    for P, r, n in zip(Ps, sweep, lost):
        print(f"  P={P:.2f}  switches {r.switches:4d}  error {np.mean(r.err):.3f}  lost {n}")
    print(f"selected P = {P_sel:.2f} (largest P with mean error within 5 % of the best; paper: 0.1-0.17)\n")

    node_run = run_in_node(rec, GreedySwitchingPolicy(P_sel))
    node_run.name = f"greedy switching, P = {P_sel:.2f} (in a FusionNode)"
    rows = [
        single(rec, ["laser"], "laser (AMCL) alone"),
        single(rec, ["depth"], "depth camera (NDT) alone"),
        single(rec, [c.name for c in CAMERAS], "ceiling cameras alone (best in view)"),
        replay(rec, GreedySwitchingPolicy(0.0), srcs, "greedy, P = 0 (plain greedy)"),
        replay(rec, GreedySwitchingPolicy(0.15), srcs, "greedy, P = 0.15 (paper's range)"),
        node_run,
        replay(rec, BlendedTransitionPolicy(GreedySwitchingPolicy(P_sel), duration=1.0), srcs,
               f"greedy P = {P_sel:.2f} + 1 s blend"),
        replay(rec, FusionFloorPolicy(0.0), srcs, "information fusion of all healthy sources (R > 0; switches: changes of the fused set)"),
        replay(rec, FusionFloorPolicy(0.6), srcs, "fusion above a floor (R > 0.6; switches: changes of the fused set)"),
    ]
    for r in rows[:3]:
        r.switches = None
    print(table_ii(rows, rec))
    plot(a.out, Ps, sw, err, P_sel, rec, node_run.chosen, minutes)
    print(f"\nplot: {a.out / 'switching_fig8.png'}   ({time.perf_counter() - t_start:.1f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
