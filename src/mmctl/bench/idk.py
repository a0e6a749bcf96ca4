"""Benchmark the IDK strategies: per-cycle time (model evaluation + solve).

Each strategy runs ``--cycles`` cycles at random whole-body configurations (arm
joints uniform in [-pi, pi], random base pose) with random desired twists (0.2 m/s,
0.3 rad/s scale) and the paper's null-space term; one cycle = ``model.update(q)``
(FK, J, and M_a when the strategy needs it) + the solve.  Side by side: the paper's
implementation (explicit ``numpy.linalg.inv`` of the 9x9 M, then the formula) and
the whole pure ``Controller.step`` (admittance, model, IDK, limits, energies).

``min-energy`` is the controller's solver as configured: with ``idk.avoid_joint_limits``
(the default) a joint nearing its position limit hands its motion over to the others,
which solves the task a second time; at these random poses that happens in about a
fifth of the cycles (``hand_over_share`` in the JSON), and those cycles make the p99.
``min-energy-no-avoidance`` is the same solve without that check, the paper's method
alone like ``paper_inv``.

``constrained-min-energy`` runs in steady motion (the previous command is this
cycle's unconstrained solution: bounds bite only where a joint limit does);
``constrained-from-rest`` starts every cycle from rest with T = 2 ms, so the
acceleration bounds are active and the QP runs every cycle (the worst case);
``constrained-osqp`` solves that same from-rest QP with OSQP (warm started) for
comparison.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from mmctl.config import Config, default_config, load_config

Vec = np.ndarray


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--cycles", type=int, default=10_000, help="cycles per strategy (>= 1)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the configurations")
    p.add_argument("--config", help="YAML config (default: built-in defaults)")
    p.add_argument("--no-osqp", action="store_true", help="skip the OSQP comparison")


def _percentiles(ns: Vec) -> dict[str, float]:
    us = ns / 1000.0
    return {"p50_us": round(float(np.percentile(us, 50)), 2),
            "p99_us": round(float(np.percentile(us, 99)), 2),
            "mean_us": round(float(us.mean()), 2)}


def _time_all(fns: dict[str, Callable[[int], Any]], n: int) -> dict[str, Vec]:
    """Time ``fn(i)`` [ns] for every fn, interleaved (i outer, fn inner) so that load
    changes on a shared machine hit every variant alike.  Progress on stderr."""
    out = {name: np.empty(n) for name in fns}
    items = [(fn, out[name]) for name, fn in fns.items()]
    step = max(1, n // 20)
    clock = time.perf_counter_ns
    for i in range(n):
        for fn, dst in items:
            t0 = clock()
            fn(i)
            dst[i] = clock() - t0
        if (i + 1) % step == 0:
            print(f"\rbench idk: {i + 1}/{n} cycles x {len(items)} variants", end="",
                  file=sys.stderr, flush=True)
    print(file=sys.stderr)
    return out


class _Cases:
    """Pre-drawn random configurations, twists and null-space targets."""

    def __init__(self, cfg: Config, n: int, seed: int) -> None:
        from mmctl.model import RobotModel

        rng = np.random.default_rng(seed)
        self.model = RobotModel(cfg.robot)
        self.q = np.concatenate((rng.uniform(-np.pi, np.pi, (n, 6)),
                                 rng.uniform(-5, 5, (n, 2)), rng.uniform(-np.pi, np.pi, (n, 1))),
                                axis=1)
        self.v = np.concatenate((0.2 * rng.normal(size=(n, 3)), 0.3 * rng.normal(size=(n, 3))),
                                axis=1)
        gain = np.array(cfg.idk.null_gain)
        self.z = gain * (self.model.q_des - self.q)
        self.gain = gain


def _paper_inv(cases: _Cases) -> Callable[[int], Vec]:
    """The paper's implementation: explicit inverses, then the formula (eq. 12-13)."""
    model = cases.model
    G = np.diag(cases.gain)
    eye = np.eye(9)

    def cycle(i: int) -> Vec:
        q = cases.q[i]
        k = model.update(q)
        M = np.zeros((9, 9))
        M[:6, :6] = k.M_a
        M[6:, 6:] = np.diag(k.M_b)
        M_inv = np.linalg.inv(M)
        J = k.J
        J_M = M_inv @ J.T @ np.linalg.inv(J @ M_inv @ J.T)
        qd: Vec = J_M @ cases.v[i] + (eye - J_M @ J) @ G @ (model.q_des - q)
        return qd

    return cycle


def _strategies(cfg: Config, cases: _Cases) -> dict[str, Callable[[int], Vec]]:
    from mmctl.control.limits import Limits
    from mmctl.control.strategies import MinEnergy, Problem, make_strategies
    from mmctl.model import RobotModel

    limits = Limits(cfg.limits, cfg.base.mecanum, cfg.arm.speedj_acceleration)
    solvers = make_strategies(cfg, limits)
    model = cases.model
    zero = np.zeros(9)
    T = 1.0 / cfg.loop.rate_hz
    needs_m = {"min-energy": True, "locomotion": False, "manipulation": False,
               "constrained-min-energy": True}
    # steady motion: the previous command is this cycle's unconstrained solution
    steady = [solvers["min-energy"].solve(Problem(model.update(q), v, q, zero, T, z))
              for q, v, z in zip(cases.q, cases.v, cases.z)]
    out: dict[str, Callable[[int], Vec]] = {}
    for name, solver in solvers.items():
        def cycle(i: int, solver: Any = solver, inertia: bool = needs_m[name],
                  prev: Any = steady if name == "constrained-min-energy" else None) -> Vec:
            q = cases.q[i]
            qd: Vec = solver.solve(Problem(model.update(q, inertia), cases.v[i], q,
                                           zero if prev is None else prev[i], T, cases.z[i]))
            return qd
        out[name] = cycle
    qp = solvers["constrained-min-energy"]

    def from_rest(i: int) -> Vec:
        q = cases.q[i]
        return qp.solve(Problem(model.update(q), cases.v[i], q, zero, T, cases.z[i]))

    out["constrained-from-rest"] = from_rest
    full_cfg = type(cfg)(**{**cfg.__dict__, "robot": type(cfg.robot)(
        **{**cfg.robot.__dict__, "full_inertia": True})})
    full_model = RobotModel(full_cfg.robot)
    full_solver = make_strategies(full_cfg, limits)["min-energy"]

    def full_cycle(i: int) -> Vec:
        q = cases.q[i]
        return full_solver.solve(Problem(full_model.update(q), cases.v[i], q, zero, T,
                                         cases.z[i]))

    out["min-energy-full-inertia"] = full_cycle
    plain = MinEnergy(cfg)  # no joint-limit avoidance: the paper's method alone

    def plain_cycle(i: int) -> Vec:
        q = cases.q[i]
        return plain.solve(Problem(model.update(q), cases.v[i], q, zero, T, cases.z[i]))

    out["min-energy-no-avoidance"] = plain_cycle
    return out


def _hand_over_share(cfg: Config, cases: _Cases, n: int) -> float:
    """The share of the first ``n`` cases in which min-energy hands a joint over (its
    solution differs from the plain solve's)."""
    from mmctl.control.limits import Limits
    from mmctl.control.strategies import MinEnergy, Problem

    limits = Limits(cfg.limits, cfg.base.mecanum, cfg.arm.speedj_acceleration)
    avoid, plain = MinEnergy(cfg, limits), MinEnergy(cfg)
    zero = np.zeros(9)
    count = 0
    for i in range(n):
        p = Problem(cases.model.update(cases.q[i]), cases.v[i], cases.q[i], zero, 0.002,
                    cases.z[i])
        count += not np.array_equal(avoid.solve(p), plain.solve(p), equal_nan=True)
    return count / n


def _osqp_cycle(cfg: Config, cases: _Cases) -> Callable[[int], Vec] | None:
    """The from-rest QP with OSQP (warm started): the same problem as ours, i.e. the
    soft task ``|qd - z|_M^2 / 2 + rho |J qd - v_d|^2 / 2`` within the same box (a hard
    equality task is primal infeasible from rest)."""
    try:
        import osqp
        from scipy import sparse
    except ImportError:
        return None
    from mmctl.control.limits import Limits

    limits = Limits(cfg.limits, cfg.base.mecanum, cfg.arm.speedj_acceleration)
    model = cases.model
    T = 1.0 / cfg.loop.rate_hz
    rho = cfg.idk.constrained.task_weight
    solver = osqp.OSQP()
    solver.setup(P=sparse.csc_matrix(np.triu(np.ones((9, 9)))), q=np.zeros(9),
                 A=sparse.csc_matrix(np.eye(9)), l=-np.ones(9), u=np.ones(9), verbose=False,
                 eps_abs=cfg.idk.constrained.eps, eps_rel=cfg.idk.constrained.eps,
                 max_iter=4000, polishing=True, warm_starting=True)
    rows, cols = np.triu_indices(9)
    order = np.lexsort((rows, cols))  # CSC order of the upper triangle
    p_rows, p_cols = rows[order], cols[order]
    zero = np.zeros(9)

    def cycle(i: int) -> Vec:
        q = cases.q[i]
        k = model.update(q)
        H = np.zeros((9, 9))
        H[:6, :6] = k.M_a
        H[6:, 6:] = np.diag(k.M_b)
        g = -(H @ cases.z[i]) - rho * (k.J.T @ cases.v[i])
        H += rho * (k.J.T @ k.J)
        lb, ub = limits.box_bounds(q, zero, T)
        solver.update(Px=H[p_rows, p_cols], q=g, l=lb, u=ub)
        x: Vec = solver.solve(raise_error=False).x
        return x

    return cycle


def _step_cycle(cfg: Config, cases: _Cases) -> Callable[[int], Any]:
    from mmctl.control.step import Controller, StepInputs

    ctl = Controller(cfg, cases.model)
    state = [ctl.initial_state()]
    rng = np.random.default_rng(1)
    forces = 20.0 * rng.normal(size=(len(cases.q), 6))
    T = 1.0 / cfg.loop.rate_hz
    qd = np.zeros(9)

    def cycle(i: int) -> Any:
        state[0], out = ctl.step(state[0], StepInputs(forces[i], cases.q[i], qd, T))
        return out

    return cycle


def run(args: argparse.Namespace) -> int:
    from mmctl.errors import ConfigError

    if args.cycles < 1:
        raise ConfigError("--cycles", args.cycles, "must be >= 1")
    cfg = load_config(args.config) if args.config else default_config()
    n = args.cycles
    cases = _Cases(cfg, n, args.seed)
    fns: dict[str, Callable[[int], Any]] = dict(_strategies(cfg, cases))
    if not args.no_osqp:
        osqp_cycle = _osqp_cycle(cfg, cases)
        if osqp_cycle is not None:
            fns["constrained-osqp"] = osqp_cycle
    paper = _paper_inv(cases)
    fns["paper_inv"] = paper
    fns["step"] = _step_cycle(cfg, cases)
    for i in range(min(n, 200)):  # warm-up
        for fn in fns.values():
            fn(i)
    raw = _time_all(fns, n)
    timings = {name: _percentiles(ns) for name, ns in raw.items()}
    paper_t = timings.pop("paper_inv")
    step_t = timings.pop("step")
    # the two implementations agree (where the task is well conditioned)
    me = fns["min-energy"]
    diffs = [float(np.abs(me(i) - paper(i)).max()) for i in range(min(n, 500))]
    ours = timings["min-energy"]
    result = {
        "strategies": timings,
        "paper_inv": paper_t,
        "ratio_p50": round(paper_t["p50_us"] / ours["p50_us"], 2),
        "ratio_p99": round(paper_t["p99_us"] / ours["p99_us"], 2),
        "step": step_t,
        "cycles": n,
        "median_abs_diff_vs_paper": float(np.median(diffs)),
        "hand_over_share": round(_hand_over_share(cfg, cases, min(n, 2000)), 3),
        "python": platform.python_version(),
        "gc_enabled": gc.isenabled(),
        "loadavg_1min": round(os.getloadavg()[0], 2),
    }
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"IDK cycle time (model evaluation + solve), {n} random configurations each, "
          f"interleaved; load average {result['loadavg_1min']} on {os.cpu_count()} CPUs")
    print(f"{'strategy':<28}{'p50 [us]':>10}{'p99 [us]':>10}{'mean [us]':>11}")
    rows = [*timings.items(), ("paper_inv (numpy inv)", paper_t), ("step (whole cycle)", step_t)]
    for name, t in rows:
        print(f"{name:<28}{t['p50_us']:>10.1f}{t['p99_us']:>10.1f}{t['mean_us']:>11.1f}")
    print(f"paper_inv / min-energy: p50 x{result['ratio_p50']}, p99 x{result['ratio_p99']} "
          f"(median |difference| {result['median_abs_diff_vs_paper']:.1e}); min-energy "
          f"hands a joint over in {100 * result['hand_over_share']:.0f} % of the poses")
    return 0
