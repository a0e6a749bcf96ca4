"""Reproduce the paper's peg-in-hole study in simulation.

Every simulated user does the task with every approach, through the control cycle
the daemon runs (the wrench pipeline from the sensor's reading, admittance, IDK,
limits; T = 2 ms) on the simulated robot's plant, faster than real time and in
parallel processes.
Prints the median table next to the paper's and the significance table (Friedman,
then Wilcoxon signed-rank with Holm-Bonferroni correction); writes results.csv,
summary.json and the figures (boxplots.png, velocity.png, energy.png) into --out.

  mmctl study                         # 27 users x (locomotion, switch, min-energy)
  mmctl study --quick                 # 3 users, a two-hole task (a smoke test)
  mmctl study --strategies locomotion switch min-energy constrained-min-energy
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from mmctl.config.control import STRATEGIES


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--users", type=int, default=None, help="number of simulated users "
                   "(default 27; 3 with --quick)")
    p.add_argument("--seed", type=int, default=0, help="population seed (default 0)")
    p.add_argument("--out", type=Path, default=Path("study-out"),
                   help="output directory (default ./study-out)")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                   help="worker processes (default: CPU count)")
    p.add_argument("--cluster", metavar="ADDRESS", default=None,
                   help="run the executions on a Dask distributed scheduler, e.g. "
                   "tcp://10.0.0.5:8786 (its workers need mmctl installed; pip install "
                   "'mmctl[cluster]'); --jobs is then ignored")
    p.add_argument("--strategies", nargs="+", choices=STRATEGIES, metavar="STRATEGY",
                   default=["locomotion", "switch", "min-energy"],
                   help=f"approaches to compare, in order (any of {', '.join(STRATEGIES)}; "
                   "default: locomotion switch min-energy)")
    p.add_argument("--quick", action="store_true", help="short task and few users")
    p.add_argument("--config", default=None, help="control configuration YAML "
                   "(default: built-in defaults)")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.add_argument("--seeds", type=int, default=1, metavar="N",
                   help="replicate the whole study over N populations (seeds SEED .. "
                   "SEED+N-1; each in OUT/seed-K) and report in how many each of the "
                   "paper's claims holds (OUT/replication.md, .json)")


class _Bar:
    """A one-line progress bar on stderr."""

    def __init__(self, total: int) -> None:
        self.total = total
        self.start = time.monotonic()
        self.tty = sys.stderr.isatty()

    def __call__(self, done: int, label: str) -> None:
        width = 30
        fill = width * done // max(self.total, 1)
        el = time.monotonic() - self.start
        eta = el / done * (self.total - done) if done else 0.0
        line = (f"study [{'#' * fill}{'.' * (width - fill)}] {done}/{self.total} "
                f"{el:5.0f} s elapsed, ~{eta:4.0f} s left  {label}")
        end = "" if self.tty and done < self.total else "\n"
        print(("\r" if self.tty else "") + line.ljust(100), end=end, file=sys.stderr,
              flush=True)


def run(args: argparse.Namespace) -> int:
    from mmctl.errors import ConfigError
    from mmctl.study.config import StudyConfig
    from mmctl.study.executor import make_executor
    from mmctl.study.plots import write_figures
    from mmctl.study.report import (
        friedman_table,
        median_ci_table,
        median_table,
        significance_table,
        write_outputs,
    )
    from mmctl.study.runner import run_study

    if args.jobs < 1:
        raise ConfigError("--jobs", args.jobs, "must be >= 1")
    if args.seeds < 1:
        raise ConfigError("--seeds", args.seeds, "must be >= 1")
    if args.seeds > 1:
        return _replicate(args)
    study = StudyConfig.make(quick=args.quick, users=args.users, seed=args.seed,
                             strategies=tuple(args.strategies), config_path=args.config)
    n = study.users * len(study.strategies)
    executor = make_executor(args.jobs, args.cluster)
    print(f"mmctl study: {study.users} users x {len(study.strategies)} approaches "
          f"({', '.join(study.strategies)}), seed {study.seed}, on {executor.name}, "
          f"{'quick task' if study.quick else 'full task'}", file=sys.stderr)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    try:
        res = run_study(study, progress=_Bar(n), executor=executor)
    finally:
        executor.close()
    wall = time.perf_counter() - wall0
    meta = {"users": study.users, "seed": study.seed, "strategies": list(study.strategies),
            "quick": study.quick, "dt": study.dt}
    analysis, doc = write_outputs(args.out, res.executions, meta)
    figures = [] if args.no_figures else write_figures(res.executions, doc["median_user"], args.out)
    # workers' CPU time, plus this process's (which includes the work when jobs == 1)
    cpu = (time.process_time() - cpu0) + (res.cpu_time if executor.name != "in-process"
                                          else 0.0)
    print(f"\nMedians over {study.users} users (simulation | paper):\n")
    print(median_table(res.executions))
    if len(study.strategies) >= 3:
        print("\nFriedman test:\n")
        print(friedman_table(analysis))
    print("\nMedians with bootstrap 95 % intervals over the users:\n")
    print(median_ci_table(analysis))
    print("\nWilcoxon signed-rank, Holm-Bonferroni corrected (alpha = 0.05), pairs tested "
          "only after a significant Friedman test; r: rank-biserial effect size:\n")
    print(significance_table(analysis))
    if doc["incomplete"]:
        print(f"\nnot finished within {study.t_max:.0f} s: {', '.join(doc['incomplete'])}")
    sim_time = sum(e.T_f for e in res.executions)
    print(f"\n{n} executions, {sim_time:.0f} s simulated in {wall:.1f} s wall, "
          f"{cpu:.1f} s CPU ({res.cycles} control cycles, "
          f"{1e6 * res.cpu_time / max(res.cycles, 1):.0f} us CPU per cycle); "
          f"median user #{doc['median_user']}")
    print(f"wrote {args.out / 'results.csv'}, {args.out / 'summary.json'}"
          + "".join(f", {f}" for f in figures))
    return 0


def _replicate(args: argparse.Namespace) -> int:
    """The study over ``--seeds`` populations, then the paper's claims tallied."""
    import json

    from mmctl.study.config import StudyConfig
    from mmctl.study.executor import make_executor
    from mmctl.study.replication import tally, tally_table
    from mmctl.study.report import write_outputs
    from mmctl.study.runner import run_study

    seeds = list(range(args.seed, args.seed + args.seeds))
    executor = make_executor(args.jobs, args.cluster)
    analyses = {}
    wall0 = time.perf_counter()
    cpu = 0.0
    try:
        for k, seed in enumerate(seeds):
            study = StudyConfig.make(quick=args.quick, users=args.users, seed=seed,
                                     strategies=tuple(args.strategies),
                                     config_path=args.config)
            n = study.users * len(study.strategies)
            print(f"mmctl study: population {k + 1}/{len(seeds)} (seed {seed}): "
                  f"{study.users} users x {len(study.strategies)} approaches on "
                  f"{executor.name}", file=sys.stderr)
            res = run_study(study, progress=_Bar(n), executor=executor)
            cpu += res.cpu_time
            meta = {"users": study.users, "seed": seed, "strategies": list(study.strategies),
                    "quick": study.quick, "dt": study.dt}
            analyses[seed], _doc = write_outputs(args.out / f"seed-{seed}", res.executions, meta)
    finally:
        executor.close()
    rows = tally(analyses)
    table = tally_table(rows, len(seeds))
    wall = time.perf_counter() - wall0
    head = (f"The paper's claims over {len(seeds)} simulated populations (seeds "
            f"{seeds[0]}..{seeds[-1]}, {args.users or 'default'} users each): a claim of a "
            "difference holds where the pair is significant (Holm, after a significant "
            "Friedman test) in the paper's direction; a claim of none where it is not.")
    (args.out / "replication.md").write_text(head + "\n\n" + table + "\n", encoding="utf-8")
    (args.out / "replication.json").write_text(json.dumps(
        {"seeds": seeds, "claims": rows, "wall_s": round(wall, 1),
         "cpu_s": round(cpu, 1)}, indent=2) + "\n", encoding="utf-8")
    print(f"\n{head}\n\n{table}\n")
    print(f"{len(seeds)} studies in {wall:.1f} s wall, {cpu:.1f} s CPU; wrote "
          f"{args.out / 'replication.md'}, {args.out / 'replication.json'} and "
          f"{args.out}/seed-*/")
    return 0
