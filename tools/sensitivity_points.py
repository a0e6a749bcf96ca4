#!/usr/bin/env python3
"""Run chosen points of a Morris screening again, one by one, and show what drives them.

`mmctl study sensitivity` draws its points with SALib's seeded sampler, so point i of
a screen (same factors, trajectories and seed) is the same point today.  This runs
only the points given (e.g. the ones around a factor's step that carries a large
elementary effect) and prints, per point: the factors' values, each claim of the
chosen metric judged as the screen judges it (its output y, the rank-biserial r,
whether it holds), and every execution's metric, T_f, completion and the fault it
stopped on.  Nothing is written.

    .venv/bin/python tools/sensitivity_points.py [--full-task] [--metric F_h]
        [--users 6] [--trajectories 4] [--seed 0] [--jobs 2] POINT [POINT ...]

Point i of trajectory t is row i of the sample, t = i // (factors + 1); the step from
point i to i + 1 changes one factor (printed with --steps).
"""

from __future__ import annotations

import argparse
import sys
import time


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("points", type=int, nargs="*", help="point indices of the screen's sample")
    p.add_argument("--full-task", action="store_true", help="the five-hole task (as the "
                   "screen's --full-task; default: the quick task)")
    p.add_argument("--metric", default="F_h", help="the claims of this metric (E, F_h, v, "
                   "x_f, T_f; default F_h)")
    p.add_argument("--users", type=int, default=None, help="users per point (default: "
                   "the screen's, 6)")
    p.add_argument("--trajectories", type=int, default=None, help="the screen's "
                   "trajectories (default 4)")
    p.add_argument("--seed", type=int, default=0, help="the screen's seed (default 0)")
    p.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    p.add_argument("--steps", action="store_true", help="list every step of the sample "
                   "(point i -> i + 1: the factor and its two values) and stop")
    args = p.parse_args()

    import numpy as np

    from mmctl.study.config import StudyConfig
    from mmctl.study.executor import make_executor
    from mmctl.study.replication import paper_claims
    from mmctl.study.sensitivity import (
        FACTORS,
        TRAJECTORIES,
        USERS,
        _paired,
        judge,
        run_points,
        sample,
    )

    factors = list(FACTORS)
    x = sample(factors, args.trajectories or TRAJECTORIES, args.seed)
    k = len(factors)
    if args.steps:
        for i in range(len(x) - 1):
            if (i + 1) % (k + 1) == 0:
                continue  # the next trajectory starts
            j = int(np.flatnonzero(x[i + 1] - x[i])[0])
            print(f"{i:3d} -> {i + 1:3d}  {factors[j].name}: {x[i][j]:.4g} -> {x[i + 1][j]:.4g}")
        return 0
    bad = [i for i in args.points if not 0 <= i < len(x)]
    if not args.points or bad:
        p.error(f"give point indices in 0..{len(x) - 1}" + (f" (got {bad})" if bad else ""))
    study = StudyConfig.make(quick=not args.full_task,
                             users=args.users if args.users is not None else USERS,
                             seed=args.seed)
    claims = [c for c in paper_claims() if c.metric == args.metric]
    if not claims:
        p.error(f"--metric {args.metric!r}: no claim of the paper has it")
    executor = make_executor(args.jobs)
    t0 = time.perf_counter()
    try:
        points, cpu = run_points(study, factors, x[args.points], executor)
    finally:
        executor.close()
    n = sum(len(e) for e in points)
    print(f"{len(args.points)} points, {n} executions, {time.perf_counter() - t0:.0f} s wall, "
          f"{cpu:.0f} s CPU in the executions")
    for i, execs in zip(args.points, points):
        values = ", ".join(f"{f.name}={v:.4g}" for f, v in zip(factors, x[i]))
        print(f"\npoint {i} (trajectory {i // (k + 1)}): {values}")
        for c in claims:
            y, r, h = judge(c, _paired(execs, c.a, c.metric), _paired(execs, c.b, c.metric))
            print(f"  {c.text()}: y = {y:+.3f}, r = {r:+.2f}, holds: {h}")
        for e in sorted(execs, key=lambda e: (e.strategy, e.user)):
            print(f"  {e.strategy:11s} user {e.user}: {args.metric} = "
                  f"{e.metric(args.metric):.3f}, T_f = {e.T_f:.1f} s, "
                  f"{'completed' if e.completed else 'UNFINISHED'}"
                  + (f", stopped: {e.stopped}" if e.stopped else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
