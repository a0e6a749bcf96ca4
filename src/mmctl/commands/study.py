"""Reproduce the paper's peg-in-hole study in simulation.

Without ANALYSIS, runs the paper's experiment: every simulated user does the task with
every approach, through the update the daemon's loop runs (tare and enable as operator
commands, the safety state machine, the wrench pipeline from the sensor's reading,
admittance, IDK, limits; T = 2 ms) on the simulated robot's plant, faster than real
time and in parallel processes.  Prints the median table next to the paper's (with the
share of samples on which a limit binds and the unfinished executions per approach) and
the significance table (Friedman, then Wilcoxon signed-rank with Holm-Bonferroni
correction: one p column, p_holm, decides; a user with an unfinished execution is
left out of every test, and the table's note says how many); writes results.csv, summary.json and the
figures (boxplots.png, velocity.png, energy.png) into --out.

  mmctl study                         # 27 users x (locomotion, switch, min-energy)
  mmctl study --quick --jobs 1        # 3 users, a two-hole task (a smoke test)
  mmctl study --strategies locomotion switch min-energy constrained-min-energy
  mmctl study --seeds 10              # the study over 10 populations, claims tallied
"""

from __future__ import annotations

import argparse
import math
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
    p.add_argument("--task", choices=("wall", "board"), default="wall",
                   help="wall: the paper's (holes in a vertical wall, horizontal "
                   "insertion, a layout drawn per seed; default); board: holes in a "
                   "horizontal board at handle height")
    p.add_argument("--config", default=None, help="control configuration YAML "
                   "(default: built-in defaults)")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.add_argument("--seeds", type=int, default=1, metavar="N",
                   help="replicate the whole study over N populations (seeds SEED .. "
                   "SEED+N-1; each in OUT/seed-K) and report in how many each of the "
                   "paper's claims holds (OUT/replication.md, .json)")
    # argparse writes a subcommand as "ANALYSIS ..." as if it were required; it is not.
    # The usage is set after the subparsers exist: theirs start from the parent's usage.
    options = p.format_usage().removeprefix("usage: ").rstrip()
    _add_analyses(p)
    indent = " " * (len(p.prog) + len("usage: ") + 1)
    p.usage = (options + f"\n{indent}[ANALYSIS [ANALYSIS's options]]").replace("%", "%%")
    p.epilog = ANALYSES_EPILOG


#: What `mmctl study --help` ends with: the analyses' example commands.
ANALYSES_EPILOG = """\
examples of the analyses (an analysis's options go after its name; mmctl study
ANALYSIS --help lists them):
  mmctl study sweep --quick --users 3 --jobs 1
  mmctl study sensitivity --trajectories 2 --users 2 --factors human.speed layout.spread
  mmctl study power --results study-out/results.csv
"""


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
        conditions,
        friedman_table,
        median_ci_table,
        median_table,
        n_note,
        significance_table,
        write_outputs,
    )
    from mmctl.study.runner import run_study, task_of

    if args.jobs < 1:
        raise ConfigError("--jobs", args.jobs, "must be >= 1")
    if args.seeds < 1:
        raise ConfigError("--seeds", args.seeds, "must be >= 1")
    if args.seeds > 1:
        return _replicate(args)
    study = StudyConfig.make(quick=args.quick, users=args.users, seed=args.seed,
                             strategies=tuple(args.strategies), config_path=args.config,
                             task=args.task)
    task = task_of(study)  # a start pose the task cannot use fails here, before the run
    n = study.users * len(study.strategies)
    executor = make_executor(args.jobs, args.cluster)
    print(f"mmctl study: {study.users} users x {len(study.strategies)} approaches "
          f"({', '.join(study.strategies)}), seed {study.seed}, on {executor.name}, "
          f"{'quick' if study.quick else 'full'} {study.task} task", file=sys.stderr)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    try:
        res = run_study(study, progress=_Bar(n), executor=executor)
    finally:
        executor.close()
    wall = time.perf_counter() - wall0
    meta = {"users": study.users, "seed": study.seed, "strategies": list(study.strategies),
            "quick": study.quick, "dt": study.dt, "task": study.task,
            "holes_approach": [[round(c, 4) for c in h.approach] for h in task.holes],
            "conditions": conditions(study)}
    analysis, doc = write_outputs(args.out, res.executions, meta)
    figures = [] if args.no_figures else write_figures(res.executions, doc["median_user"],
                                                       args.out, doc)
    # workers' CPU time, plus this process's (which includes the work when jobs == 1)
    cpu = (time.process_time() - cpu0) + (res.cpu_time if executor.name != "in-process"
                                          else 0.0)
    print(f"\nMedians over {study.users} users (simulation | paper):\n")
    print(median_table(res.executions))
    if len(study.strategies) >= 3:
        print("\nFriedman test:\n")
        print(friedman_table(analysis))
    tested_n, excluded = doc["tested_users"], len(doc["excluded_users"])
    print(f"\nMedians with bootstrap 95 % intervals over the {n_note(tested_n, excluded)} "
          "tested:\n")
    print(median_ci_table(analysis))
    print("\nWilcoxon signed-rank, Holm-Bonferroni corrected (alpha = 0.05), pairs tested "
          "only after a significant Friedman test; r: rank-biserial effect size:\n")
    print(significance_table(analysis, tested_n, excluded=excluded))
    if doc["incomplete"]:
        print(f"\nnot finished (time limit {study.t_max:.0f} s, or stopped by a fault): "
              f"{len(doc['incomplete'])} of {n} executions, {', '.join(doc['incomplete'])}; "
              f"users {', '.join(map(str, doc['excluded_users']))} excluded from the tests")
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
    from mmctl.study.report import conditions, tested, users_of, write_outputs
    from mmctl.study.runner import run_study

    seeds = list(range(args.seed, args.seed + args.seeds))
    executor = make_executor(args.jobs, args.cluster)
    analyses = {}
    tested_users: dict[int, int] = {}  # per seed: the users its tests ran on
    wall0 = time.perf_counter()
    cpu = 0.0
    try:
        for k, seed in enumerate(seeds):
            study = StudyConfig.make(quick=args.quick, users=args.users, seed=seed,
                                     strategies=tuple(args.strategies),
                                     config_path=args.config, task=args.task)
            n = study.users * len(study.strategies)
            print(f"mmctl study: population {k + 1}/{len(seeds)} (seed {seed}): "
                  f"{study.users} users x {len(study.strategies)} approaches on "
                  f"{executor.name}", file=sys.stderr)
            res = run_study(study, progress=_Bar(n), executor=executor)
            cpu += res.cpu_time
            meta = {"users": study.users, "seed": seed, "strategies": list(study.strategies),
                    "quick": study.quick, "dt": study.dt, "task": study.task,
                    "conditions": conditions(study)}
            analyses[seed], _doc = write_outputs(args.out / f"seed-{seed}", res.executions, meta)
            tested_users[seed] = users_of(tested(res.executions))
    finally:
        executor.close()
    rows = tally(analyses, users=tested_users)  # decided by each seed's tables' own p_holm
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


# --- analyses over many studies: `mmctl study sweep`, `mmctl study sensitivity` --------

def _add_common(q: argparse.ArgumentParser, out: str, users_help: str) -> None:
    q.add_argument("--users", type=int, default=None, help=users_help)
    q.add_argument("--seed", type=int, default=0, help="population seed (default 0)")
    q.add_argument("--out", type=Path, default=Path(out), help=f"output directory "
                   f"(default ./{out})")
    q.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                   help="worker processes (default: CPU count)")
    q.add_argument("--cluster", metavar="ADDRESS", default=None,
                   help="run the executions on a Dask distributed scheduler (see mmctl study)")
    q.add_argument("--config", default=None, help="control configuration YAML "
                   "(default: built-in defaults)")
    q.add_argument("--no-figures", action="store_true", help="skip the PNG figure")


def _add_analyses(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="analysis", metavar="ANALYSIS", title="analyses (optional)",
                           help="without one, the paper's experiment runs; with one, that "
                           "analysis instead: sweep, sensitivity or power")
    sw = sub.add_parser(
        "sweep", help="min-energy with the base's weight s*M_b in its IDK and either "
        "null-space projector, Ē against x_f (sweep.csv, sweep.png)",
        description="The inertia-weighting sweep (mmctl.study.sweep): the min-energy IDK "
        "with the base's inertia scaled by s in its weighting and the dynamically "
        "consistent or the ordinary null-space projector, plus the coupled-inertia "
        "ablation and the locomotion approach, for the same users, optionally with the "
        "null-space gain G scaled (--gains); median E and x_f per setting, x_f also read "
        "0.5, 1, 2 s after T_f and at the end of the hold. Writes sweep.csv and sweep.png "
        "(and sweep-gain.png with several gains).")
    _add_common(sw, "sweep-out", "number of simulated users (default 27; 3 with --quick)")
    sw.add_argument("--quick", action="store_true", help="the short two-hole task")
    sw.add_argument("--scales", type=float, nargs="+", default=None, metavar="S",
                    help="base weight scales (default: 10^(k/4), k = -4..4: 0.1 .. 10)")
    sw.add_argument("--projectors", nargs="+", choices=("dynamic", "euclidean"),
                    default=["dynamic", "euclidean"], help="null-space projectors")
    sw.add_argument("--no-coupled", action="store_true",
                    help="skip the coupled-inertia ablation")
    sw.add_argument("--gains", type=float, nargs="+", default=None, metavar="G",
                    help="scales g > 0 of the null-space gain G's arm entries "
                    "(idk.null_gain; the paper's G = diag(1,1,1,1,1,1,0,0,0) [1/s] is g = 1; "
                    "each scaled entry must stay <= 100/s, the key's range), one setting "
                    "per scale, projector and gain, in the min-energy settings only "
                    "(locomotion keeps the configured G). Default: 1 only (the grid of "
                    "--scales x --projectors). With several gains sweep-gain.png also "
                    "draws Ē against x_f read at T_f, 0.5, 1, 2 s after it and at the "
                    "hold's end")
    sw.set_defaults(_run=run_sweep)
    se = sub.add_parser(
        "sensitivity", help="Morris screening (SALib) of which factors (people, plant, "
        "layout) move the paper's claims (sensitivity.csv, .json, .png)",
        description="Morris screening (mmctl.study.sensitivity): a small study per Morris "
        "point over the population's medians, the plant and the layout; per claim of the "
        "paper, the factors ranked by mu* and where in each range the claim holds. Writes "
        "sensitivity.csv, sensitivity.json and sensitivity.png.")
    _add_common(se, "sensitivity-out", "simulated users per Morris point (default 6)")
    se.add_argument("--trajectories", type=int, default=None, metavar="R",
                    help="Morris trajectories (default 4; points = R x (factors + 1))")
    se.add_argument("--factors", nargs="+", default=None, metavar="NAME",
                    help="screen only these factors (default: all; names as in "
                    "sensitivity.csv, e.g. human.stiffness arm.speedj_acceleration)")
    se.add_argument("--full-task", action="store_true",
                    help="the full five-hole task per point (default: the quick task)")
    se.set_defaults(_run=run_sensitivity)
    from mmctl.commands.study_power import add_parser as add_power

    add_power(sub)


def run_sweep(args: argparse.Namespace) -> int:
    from mmctl.errors import ConfigError
    from mmctl.study.config import StudyConfig
    from mmctl.study.executor import make_executor
    from mmctl.study.report import conditions
    from mmctl.study.sweep import (
        DEFAULT_GAINS,
        DEFAULT_SCALES,
        run_sweep,
        settings,
        sweep_table,
        write_sweep,
    )

    if args.jobs < 1:
        raise ConfigError("--jobs", args.jobs, "must be >= 1")
    for g in args.gains or ():
        if not (math.isfinite(g) and g > 0.0):
            raise ConfigError("--gains", g, "each gain scale must be a number > 0")
    study = StudyConfig.make(quick=args.quick, users=args.users, seed=args.seed,
                             config_path=args.config)
    grid = settings(tuple(args.scales) if args.scales else DEFAULT_SCALES,
                    tuple(dict.fromkeys(args.projectors)), not args.no_coupled,
                    tuple(dict.fromkeys(args.gains)) if args.gains else DEFAULT_GAINS)
    base_cfg = study.control_config("min-energy")
    for g in grid:  # a gain the configuration cannot take: one line now, not in a worker
        try:
            g.config(base_cfg)
        except ConfigError as exc:
            raise ConfigError("--gains", g.gain_scale, f"makes {exc.key} = "
                              f"{list(exc.value) if isinstance(exc.value, list) else exc.value}"
                              f": {exc.allowed}") from None
    n = study.users * (len(grid) + 1)
    executor = make_executor(args.jobs, args.cluster)
    print(f"mmctl study sweep: {len(grid)} min-energy settings + locomotion x "
          f"{study.users} users, seed {study.seed}, on {executor.name}, "
          f"{'quick task' if study.quick else 'full task'}", file=sys.stderr)
    wall0 = time.perf_counter()
    try:
        res = run_sweep(study, grid, executor, _Bar(n))
    finally:
        executor.close()
    wall = time.perf_counter() - wall0
    meta = {"users": study.users, "seed": study.seed, "quick": study.quick, "task": study.task,
            "conditions": conditions(study)}
    paths = write_sweep(args.out, res, meta, figure=not args.no_figures)
    print(f"\nInertia-weighting sweep, medians over {study.users} users:\n")
    print(sweep_table(res.rows))
    dom = [r.setting.label for r in res.rows if r.dominates and r.setting is not None]
    print("\n" + (f"dominating the simulation's min-energy at the paper's setting (s = 1, "
                  f"dynamic) on both median E and x_f: {', '.join(dom)}"
                  if dom else "no setting has both a lower median E and a lower median x_f "
                  "than the simulation's min-energy at the paper's setting (s = 1, dynamic)"))
    print(f"\n{n} executions in {wall:.1f} s wall, {res.cpu_time:.1f} s CPU in the "
          f"executions ({res.cycles} control cycles); wrote "
          + ", ".join(str(p) for p in paths))
    return 0


def run_sensitivity(args: argparse.Namespace) -> int:
    from mmctl.errors import ConfigError
    from mmctl.study.config import StudyConfig
    from mmctl.study.executor import make_executor
    from mmctl.study.report import conditions
    from mmctl.study.sensitivity import (
        FACTORS,
        TRAJECTORIES,
        USERS,
        analyse,
        check_factors,
        factor_by_name,
        run_points,
        sample,
        sensitivity_table,
        write_sensitivity,
    )

    if args.jobs < 1:
        raise ConfigError("--jobs", args.jobs, "must be >= 1")
    study = StudyConfig.make(quick=not args.full_task,
                             users=args.users if args.users is not None else USERS,
                             seed=args.seed, config_path=args.config)
    factors = ([factor_by_name(f) for f in args.factors] if args.factors else list(FACTORS))
    check_factors(study, factors)
    r = args.trajectories if args.trajectories is not None else TRAJECTORIES
    x = sample(factors, r, study.seed)
    n = len(x) * study.users * len(study.strategies)
    executor = make_executor(args.jobs, args.cluster)
    print(f"mmctl study sensitivity: {len(factors)} factors, {r} trajectories = {len(x)} "
          f"points x {study.users} users x {len(study.strategies)} approaches, seed "
          f"{study.seed}, on {executor.name}", file=sys.stderr)
    wall0 = time.perf_counter()
    try:
        points, cpu = run_points(study, factors, x, executor, _Bar(n))
    finally:
        executor.close()
    wall = time.perf_counter() - wall0
    doc = analyse(factors, x, points, study.seed)
    doc.update({"trajectories": r, "users": study.users, "seed": study.seed,
                "quick": study.quick, "task": study.task, "points_n": len(x),
                "conditions": conditions(study)})
    paths = write_sensitivity(args.out, doc, figure=False)
    if not args.no_figures:  # the chart with its caption (n, conditions) from the document
        from mmctl.study.plots import write_sensitivity_figure

        paths.append(write_sensitivity_figure(doc, args.out / "sensitivity.png"))
    print(f"\nMorris screening of the paper's claims ({len(x)} points of {study.users} "
          f"users; a claim holds where |r| meets r_crit = {doc['r_crit']:.3f}):\n")
    print(sensitivity_table(doc))
    print(f"\n{n} executions in {wall:.1f} s wall, {cpu:.1f} s CPU in the executions; "
          "wrote " + ", ".join(str(p) for p in paths))
    return 0
