"""`mmctl study power`: how strong each of the paper's claims is and how many people a
real study needs (:mod:`mmctl.study.power`), from the paper's numbers alone or with a
simulated study's results.csv beside them."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any


def add_parser(sub: Any) -> None:
    """The `power` analysis under `mmctl study`."""
    pw = sub.add_parser(
        "power", help="effect sizes, equivalence tests and the participants each of the "
        "paper's claims needs (power.md, power.json)",
        description="For each of the paper's 15 claims: the effect its p_corr implies "
        "(Holm undone), and the participants a real study needs for the given power at "
        "alpha with Holm over the three pairs (Wilcoxon via the paired t and the ARE "
        "3/pi). With --results (a study's results.csv): the simulation's matched-pairs "
        "effect and median difference beside the paper's, TOST for the paper's "
        "'no difference' claims, and the sample size of the simulation's effect over "
        "the SD the paper's own test implies. Reads results, runs no executions.",
        epilog="example: mmctl study --out study-out && mmctl study power --results "
        "study-out/results.csv")
    pw.add_argument("--results", type=Path, default=None, metavar="CSV",
                    help="a study's results.csv (e.g. study-out/results.csv)")
    pw.add_argument("--power", type=float, default=0.8, help="wanted power (default 0.8)")
    pw.add_argument("--alpha", type=float, default=0.05, help="significance level "
                    "(default 0.05; Holm over the three pairs of a metric)")
    pw.add_argument("--check", type=int, default=0, metavar="REPS",
                    help="Monte Carlo: run the project's own Friedman + Wilcoxon + Holm "
                    "pipeline REPS times at each planned size of the paper's effects "
                    "(default 0: none; 400 takes about a minute)")
    pw.add_argument("--out", type=Path, default=Path("power-out"),
                    help="output directory (default ./power-out)")
    pw.set_defaults(_run=run)


def run(args: argparse.Namespace) -> int:
    from mmctl.errors import ConfigError
    from mmctl.study import power as pw

    if not 0.0 < args.power < 1.0:
        raise ConfigError("--power", args.power, "must be between 0 and 1")
    if not 0.0 < args.alpha < 0.5:
        raise ConfigError("--alpha", args.alpha, "must be between 0 and 0.5")
    if args.check < 0:
        raise ConfigError("--check", args.check, "must be >= 0")
    values = None
    if args.results is not None:
        if not args.results.is_file():
            raise ConfigError("--results", str(args.results), "is not a file (a study's "
                              "results.csv)")
        values = pw.read_values(str(args.results))
        missing = [a for a in ("locomotion", "switch", "min-energy") if a not in values]
        if missing:
            raise ConfigError("--results", str(args.results),
                              f"has no executions of {', '.join(missing)} (the paper's three "
                              "approaches are needed)")
    sizes = pw.size_table(values, args.power, args.alpha)
    parts = [(f"## Participants for {args.power:.0%} power at alpha = {args.alpha:g}, Holm over "
             "three pairs\n"),
             ("Planned at Holm's first step (alpha / 3) for a Wilcoxon signed-rank test: the "
             "paired t's size (noncentral t) divided by the ARE 3/pi. d_z (paper) = z / "
             "sqrt(27) from the paper's p_corr with Holm undone; a p_corr at the paper's "
             "floor (1.682e-5) gives a lower bound on z, so its n is an upper bound. "
             "The SD of a-b is the one the paper's test implies (|median difference| x "
             "sqrt(27) / z): the paper gives no spread in numbers; an assumption.\n"),
             pw.size_markdown(sizes)]
    claims: list[pw.ClaimRow] = []
    if values is not None:
        n = len(values["locomotion"]["E"])
        claims = pw.claims_table(values, args.alpha)
        parts += [f"\n## The paper's claims beside the simulation ({n} users)\n",
                  ("r_rb: matched-pairs rank-biserial correlation (a > b positive); the paper's "
                  "is the one its p_corr implies without ties (≥: a bound, at its floor). "
                  "TOST: two one-sided Wilcoxon tests against ±margin (the metric's unit; "
                  "margins and their reasons in docs/study.md); equivalent when p < alpha. "
                  "'inconclusive': neither different nor shown equivalent.\n"),
                  pw.claims_markdown(claims, args.alpha)]
    checks: list[dict[str, Any]] = []
    if args.check:
        rows = ["| claim | planned n | power in the pipeline |", "|---|---:|---:|"]
        for r in sizes:
            if r.paper_claim == "≈" or r.n_paper is None:
                continue
            # the pipeline's pair 0 is (a, b); differences in SD units: d_z
            got = pw.monte_carlo_power(r.d_z_paper, 1.0, r.n_paper, reps=args.check,
                                       alpha=args.alpha, seed=len(checks))
            checks.append({"metric": r.metric, "a": r.a, "b": r.b, "n": r.n_paper,
                           "power": got})
            rows.append(f"| {r.metric}: {r.a} vs {r.b} | {r.n_paper} | {got:.2f} |")
        parts += [f"\n## Monte Carlo check ({args.check} simulated studies each)\n",
                  "\n".join(rows)]
    text = "\n".join(parts) + "\n"
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "power.md").write_text(text, encoding="utf-8")

    def clean(x: Any) -> Any:
        if isinstance(x, float) and not math.isfinite(x):
            return None
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        return x

    doc = {"power": args.power, "alpha": args.alpha,
           "sizes": [{k: clean(v) for k, v in r._asdict().items()} for r in sizes],
           "claims": [{k: clean(v) for k, v in r._asdict().items()} for r in claims],
           "margins": {m: g._asdict() for m, g in pw.MARGINS.items()},
           "monte_carlo": checks}
    (args.out / "power.json").write_text(json.dumps(doc, indent=2, ensure_ascii=False) + "\n",
                                         encoding="utf-8")
    print(text)
    print(f"wrote {args.out / 'power.md'} and {args.out / 'power.json'}")
    return 0
