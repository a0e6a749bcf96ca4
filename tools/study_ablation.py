#!/usr/bin/env python3
"""Which of the paper's claims come from the control law and which from the
simulation's modelling choices: the study under each ablation of
:mod:`mmctl.study.ablation` (press cost 0, dead band 0, no switching-policy delay, no
slip), the same users throughout; each claim's rank-biserial r beside the baseline's.

Printed (and written to OUT/ablation.md, OUT/ablation.json): the table, the users,
the task, the wall and CPU time.

    .venv/bin/python tools/study_ablation.py [--users 9] [--jobs 2] [--quick]
        [--out ablation-out]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--users", type=int, default=9, help="simulated users (default 9)")
    p.add_argument("--seed", type=int, default=0, help="population seed (default 0)")
    p.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    p.add_argument("--quick", action="store_true", help="the short two-hole task")
    p.add_argument("--out", type=Path, default=Path("ablation-out"))
    args = p.parse_args()
    from mmctl.study.ablation import ABLATIONS, run_ablations, table
    from mmctl.study.config import StudyConfig

    study = StudyConfig.make(quick=args.quick, users=args.users, seed=args.seed)
    n = len(ABLATIONS) * study.users * len(study.strategies)
    t0 = time.perf_counter()
    c0 = time.process_time()

    def progress(done: int, what: str) -> None:
        print(f"\r{done}/{n} {what:40}", end="", file=sys.stderr, flush=True)

    res = run_ablations(study, ABLATIONS, jobs=args.jobs, progress=progress)
    wall = time.perf_counter() - t0
    md, rows = table(res)
    unfinished = {k: sum(not e.completed for e in v) for k, v in res.items()}
    head = (f"Ablations: {study.users} users (seed {study.seed}), "
            f"{'quick' if study.quick else 'full'} {study.task} task, {n} executions in "
            f"{wall:.0f} s wall; unfinished per ablation: {unfinished}. Cells: the "
            "matched-pairs rank-biserial r of a − b (users who finished every approach). "
            "'rests on': the ablations without which a reproduced difference falls below "
            "|r| = 0.25 or turns.")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ablation.md").write_text(head + "\n\n" + md + "\n", encoding="utf-8")
    (args.out / "ablation.json").write_text(json.dumps(
        {"users": study.users, "seed": study.seed, "quick": study.quick,
         "ablations": [{"name": a.name, "what": a.what} for a in ABLATIONS],
         "unfinished": unfinished, "claims": rows, "wall_s": round(wall, 1),
         "cpu_s_parent": round(time.process_time() - c0, 1)}, indent=2,
        ensure_ascii=False) + "\n", encoding="utf-8")
    print(f"\n{head}\n\n{md}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
