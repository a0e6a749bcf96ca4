"""Measure what telemetry costs the control loop: the same body, telemetry off vs on.

:func:`windows_on_daemon` does it on a running daemon (`mmctl bench loop --telemetry`):
consecutive measurement windows alternate off / on (off, on, off, on, ...) with one
publisher recording to an ``.rrd`` throughout; an "on" window installs the daemon's
sample hook, an "off" window removes it.  Timings come from the daemon's own timing
ring and are pooled per condition.

:func:`compare` runs a real :class:`~mmctl.runtime.loop.CycleLoop` for several phases in
one process, alternating off / on (off, on, off, on, ...), each phase with a fresh
timing ring, and pools the per-cycle timings of each condition.  "On" means the whole
path: the body calls the hook (the cycle written into the sample ring), and the
publisher thread batches to a real rerun sink (an ``.rrd`` file) at the configured
rates.  `mmctl bench loop --telemetry` and ``tools/telemetry_bench.py`` print the result.
"""

from __future__ import annotations

import sys
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from mmctl.config import Config
from mmctl.errors import MmctlError
from mmctl.runtime.loop import CycleLoop, Tick
from mmctl.runtime.timing import TimingRing, TimingSnapshot, TimingStats, cycle_rows, summarize
from mmctl.telemetry.rerun_sink import Destinations
from mmctl.telemetry.service import TelemetryService

#: body_for(service, origin_ns) -> the loop body; the body installs ``service.hook(core)``
#: (None when telemetry is off)
BodyFactory = Callable[[TelemetryService, int], Callable[[Tick], None]]


class Phase(NamedTuple):
    """One phase: telemetry on or off, its timing snapshot and publisher counters."""

    telemetry: bool
    snapshot: TimingSnapshot
    published: int
    dropped: int
    flush_max_us: float


def _pool(phases: list[Phase], on: bool) -> TimingStats:
    snaps = [p.snapshot for p in phases if p.telemetry == on]
    def cat(field: str) -> Any:
        return np.concatenate([getattr(s, field) for s in snaps])

    return summarize(TimingSnapshot(cat("deadline_ns"), cat("latency_ns"), cat("compute_ns"),
                                    cat("slack_ns"), cat("missed"), first_index=0))


def run_phase(cfg: Config, body_for: BodyFactory, seconds: float, telemetry: bool,
              record: Path | None) -> Phase:
    """One loop run of ``seconds`` [s]; with telemetry, a publisher recording to ``record``."""
    import time

    cycles = int(seconds * cfg.loop.rate_hz)
    ring = TimingRing(cycles + 16)
    service = TelemetryService(cfg, Destinations(record=str(record)) if telemetry else None)
    loop_box: dict[str, Any] = {}
    origin = time.perf_counter_ns()
    service.start(ring)
    body = body_for(service, origin)

    def counted(tick: Tick) -> None:
        body(tick)
        if tick.index + 1 >= cycles:
            loop_box["loop"].stop()

    loop = CycleLoop(counted, rate_hz=cfg.loop.rate_hz, spin_margin=cfg.loop.spin_margin,
                     max_consecutive_misses=10**9, max_total_misses=10**9, ring=ring,
                     rt_priority=cfg.loop.rt_priority, cpu_affinity=cfg.loop.cpu_affinity)
    loop_box["loop"] = loop
    loop.start()
    loop.wait(seconds * 20 + 30)
    loop.join(5.0)
    pub = service.publisher
    service.close()
    stats = pub.stats() if pub is not None else {}
    if pub is not None and pub.error is not None:
        raise pub.error
    return Phase(telemetry, ring.snapshot(), int(stats.get("published", 0)),
                 int(stats.get("dropped", 0)), float(stats.get("flush_max_us", 0.0)))


def compare(cfg: Config, body_for: BodyFactory, seconds: float = 10.0, phases: int = 4,
            record_dir: Path | None = None) -> dict[str, Any]:
    """Alternate ``phases`` runs (off first) of ``seconds / phases`` each; pooled figures.

    Returns {"off": stats, "on": stats, "compute_p99_growth": fraction,
    "misses_off"/"misses_on", "published", "dropped", "flush_max_us", "phases"}.
    """
    sys.setswitchinterval(cfg.loop.switch_interval)
    tmp = None
    if record_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="mmctl-telemetry-bench-")
        record_dir = Path(tmp.name)
    try:
        done = []
        for i in range(max(2, phases)):
            on = i % 2 == 1
            rec = record_dir / f"bench-phase{i}.rrd" if on else None
            done.append(run_phase(cfg, body_for, seconds / max(2, phases), on, rec))
    finally:
        if tmp is not None:
            tmp.cleanup()
    return _report(done)


def overlapping_misses(snap: TimingSnapshot, lead_ns: int, starts: np.ndarray,
                       ends: np.ndarray) -> int:
    """How many of the snapshot's late cycles overlap a publisher work interval.

    A cycle counts when one of ``[starts[k], ends[k]]`` [perf_counter ns] intersects
    ``[its deadline - lead_ns, its end]``: the publisher was working while the loop
    woke up (the loop's sleep ends ``lead_ns``, its spin margin, before the deadline)
    or ran the late cycle, so it may have delayed it.  Work in the idle time before
    that is what the publisher is paced into and does not count.  An upper bound on
    the misses telemetry caused.
    """
    late = np.flatnonzero(snap.missed > 0)
    n = 0
    for i in late:
        a = int(snap.deadline_ns[i]) - lead_ns
        b = int(snap.deadline_ns[i] + snap.latency_ns[i] + snap.compute_ns[i])
        if np.any((starts < b) & (ends > a)):
            n += 1
    return n


def _window_pairs(phases: list[Phase]) -> list[tuple[Phase, Phase]]:
    """The adjacent (off, on) window pairs that both hold cycles."""
    return [(off, on) for off, on in zip(phases[::2], phases[1::2], strict=False)
            if not off.telemetry and on.telemetry and len(off.snapshot) and len(on.snapshot)]


def _pairs(phases: list[Phase]) -> dict[str, Any]:
    """Growth of compute p99 within each adjacent (off, on) window pair, and its median.

    The pooled p99 of each condition is what the target speaks of, but a burst of load
    from elsewhere on the machine that lands in a few windows moves it; the median of
    the pairwise growths ignores such a burst unless it hits most pairs.
    """
    growths, extra_misses = [], []
    for off, on in _window_pairs(phases):
        p_off = float(np.percentile(off.snapshot.compute_ns, 99))
        p_on = float(np.percentile(on.snapshot.compute_ns, 99))
        growths.append(p_on / p_off - 1.0)
        extra_misses.append(int(on.snapshot.missed.sum()) - int(off.snapshot.missed.sum()))
    if not growths:
        return {}
    return {"compute_p99_growth_pairs": [round(g, 4) for g in growths],
            "compute_p99_growth_pair_median": round(float(np.median(growths)), 4),
            "extra_misses_pairs": extra_misses}


MIN_PAIRS = 5
"""Fewest (off, on) window pairs a confidence interval is given for."""


class _PairHistograms(NamedTuple):
    """Per (off, on) window pair: compute-time histograms [1 us bins], cycles, misses."""

    off: np.ndarray  # (pairs, bins) counts
    on: np.ndarray
    cycles: np.ndarray  # (pairs, 2): off, on
    misses: np.ndarray  # (pairs, 2)


def _pair_histograms(phases: list[Phase]) -> _PairHistograms | None:
    """Histograms up to the largest window p99: a pool of windows has its p99 at or
    below that (each window has 99 % of its cycles there), so longer cycles all go into
    the last bin without changing any pooled p99, and a stall of the machine does not
    make the histograms tens of thousands of bins wide."""
    pairs = _window_pairs(phases)
    if len(pairs) < MIN_PAIRS:
        return None
    cap = max(int(np.percentile(p.snapshot.compute_ns, 99, method="higher"))
              for pair in pairs for p in pair) // 1000
    bins = cap + 2

    def hist(p: Phase) -> np.ndarray:
        us = np.minimum(p.snapshot.compute_ns // 1000, bins - 1)
        return np.bincount(us, minlength=bins).astype(float)

    return _PairHistograms(
        np.array([hist(a) for a, _ in pairs]), np.array([hist(b) for _, b in pairs]),
        np.array([[len(a.snapshot), len(b.snapshot)] for a, b in pairs], dtype=float),
        np.array([[a.snapshot.missed.sum(), b.snapshot.missed.sum()] for a, b in pairs],
                 dtype=float))


def _quantile_us(hist: np.ndarray, q: float) -> np.ndarray:
    """The ``q`` quantile [us] of each pooled histogram (rows of 1 us bins): the upper
    edge of the first bin where the cumulative count reaches ``q`` of the total."""
    cum = np.cumsum(hist, axis=-1)
    edges: np.ndarray = np.argmax(cum >= q * cum[..., -1:], axis=-1) + 1.0
    return edges


def growth_interval(phases: list[Phase], confidence: float = 0.95, resamples: int = 2000,
                    seed: int = 0) -> dict[str, Any]:
    """Confidence intervals of the telemetry cost, resampling whole (off, on) pairs.

    A window pair is the unit that is independent of the others (the machine's bursts
    last a window or two; cycles within a window are not independent), so a bootstrap
    over pairs (scipy's BCa) gives the uncertainty of: the pooled compute p99 growth
    (each resample pools its pairs' histograms, 1 us bins) and the extra misses per
    10^5 cycles with telemetry on.  {} with fewer than :data:`MIN_PAIRS` pairs.
    """
    from scipy import stats

    h = _pair_histograms(phases)
    if h is None:
        return {}

    def weights(idx: np.ndarray) -> np.ndarray:  # (..., n) resampled pair indices -> counts
        flat = idx.reshape(-1, idx.shape[-1])
        w = np.zeros((flat.shape[0], len(h.off)))
        np.add.at(w, (np.arange(flat.shape[0])[:, None], flat), 1.0)
        return w.reshape(*idx.shape[:-1], len(h.off))

    # ``axis``: scipy's vectorized statistic signature; resamples run along the last axis
    def growth(idx: np.ndarray, axis: int = -1) -> np.ndarray:
        w = weights(idx)
        g: np.ndarray = _quantile_us(w @ h.on, 0.99) / _quantile_us(w @ h.off, 0.99) - 1.0
        return g

    def extra_misses(idx: np.ndarray, axis: int = -1) -> np.ndarray:
        w = weights(idx)
        rate = (w @ h.misses) / (w @ h.cycles)
        extra: np.ndarray = 1e5 * (rate[..., 1] - rate[..., 0])
        return extra

    idx = np.arange(len(h.off))
    out: dict[str, Any] = {"confidence": confidence, "pairs": len(idx)}
    for key, stat in (("compute_p99_growth", growth), ("extra_misses_per_1e5", extra_misses)):
        with warnings.catch_warnings():  # a degenerate statistic (0/0 in BCa) is handled below
            warnings.simplefilter("ignore", stats.DegenerateDataWarning)
            warnings.simplefilter("ignore", RuntimeWarning)
            res = stats.bootstrap((idx,), stat, vectorized=True, n_resamples=resamples,
                                  confidence_level=confidence, method="BCa", batch=200,
                                  rng=np.random.default_rng(seed))
        lo, hi = res.confidence_interval
        point = float(stat(idx))
        if not np.isfinite(lo) or not np.isfinite(hi):  # degenerate (e.g. no misses at all)
            lo = hi = point
        out[key] = round(point, 4)
        out[key + "_ci"] = [round(float(lo), 4), round(float(hi), 4)]
    return out


def _report(phases: list[Phase], busy: tuple[np.ndarray, np.ndarray] | None = None,
            lead_ns: int = 0, hook_ns: np.ndarray | None = None) -> dict[str, Any]:
    s_off, s_on = _pool(phases, False), _pool(phases, True)
    growth = ((s_on.compute_p99_us - s_off.compute_p99_us) / s_off.compute_p99_us
              if s_off.cycles else 0.0)
    out = {
        "off": s_off.as_dict(),
        "on": s_on.as_dict(),
        "compute_p99_growth": round(growth, 4),
        "misses_off": s_off.missed,
        "misses_on": s_on.missed,
        "published": sum(p.published for p in phases),
        "dropped": sum(p.dropped for p in phases),
        "flush_max_us": max(p.flush_max_us for p in phases),
        "phases": len(phases),
        **_pairs(phases),
        "interval": growth_interval(phases),
    }
    if hook_ns is not None:
        on_hook = np.concatenate([cycle_rows(hook_ns, p.snapshot) for p in phases if p.telemetry]
                                 + [np.zeros(0, np.int64)]) / 1e3
        on_hook = on_hook[on_hook > 0]
        if on_hook.size:
            out["hook_p50_us"] = round(float(np.percentile(on_hook, 50)), 2)
            out["hook_p99_us"] = round(float(np.percentile(on_hook, 99)), 2)
    for key, on in (("misses_overlapping_publisher_off", False),
                    ("misses_overlapping_publisher_on", True)):
        # None: the publisher ran in another process (it never holds the loop's GIL)
        out[key] = (sum(overlapping_misses(p.snapshot, lead_ns, *busy)
                        for p in phases if p.telemetry is on) if busy is not None else None)
    return out


def windows_on_daemon(daemon: Any, seconds: float, phases: int = 10,
                      record_dir: Path | None = None, aa: bool = False,
                      settle: float | None = None) -> dict[str, Any]:
    """Alternate telemetry off/on windows of ``seconds / phases`` on a running daemon.

    daemon: started (loop running) and armed, with ``cfg``, ``ring``, ``sample_hook`` and
    ``_t0_ns``; its own sample hook is restored at the end.  One publisher (recording to
    an ``.rrd``) runs for the whole measurement; an "on" window installs its hook (the
    loop builds samples, the publisher batches and sends them), an "off" window removes
    it (the publisher idles).  Many short windows average out the machine's drift.
    Returns the same dict as :func:`compare`.  The daemon's ring must hold at least one
    window of cycles.  aa: an A/A check -- the "on" windows install no hook either, so
    the figures measure the noise of the comparison itself.  settle: time not counted
    after each switch [s] (default: two publisher wake-ups, at least 0.15 s: the last
    batch of an "on" window is sent in the "off" window after it).
    """
    import time

    cfg, ring = daemon.cfg, daemon.ring
    n = max(2, phases)
    window = seconds / n
    tmp = None
    if record_dir is None:
        tmp = tempfile.TemporaryDirectory(prefix="mmctl-telemetry-bench-")
        record_dir = Path(tmp.name)
    if settle is None:
        settle = max(0.15, 2.0 / cfg.telemetry.scene_rate)
    saved = daemon.sample_hook
    done: list[Phase] = []
    service = TelemetryService(cfg, Destinations(record=str(record_dir / "bench.rrd")))
    try:
        service.start(ring)
        pub = service.publisher
        if pub is None or pub.ring is None:
            raise MmctlError("the telemetry publisher did not start")
        hook = service.hook(daemon.core)
        time.sleep(1.0)  # start-up (the publisher's process, rerun's threads) is not steady state
        for i in range(n):
            on = i % 2 == 1
            daemon.sample_hook = hook if on and not aa else None
            time.sleep(settle)  # the last batch of an "on" window is still being sent
            c0, p0, d0 = ring.count, pub.published, pub.ring.dropped
            time.sleep(window)
            snap = ring.snapshot(ring.count - c0)
            done.append(Phase(on, snap, pub.published - p0 if on else 0,
                              pub.ring.dropped - d0, pub.flush_ns_max / 1e3))
        daemon.sample_hook = None
        service.close()
        if pub.error is not None:
            raise pub.error
        busy = pub.busy.intervals() if pub.busy is not None else None
    finally:
        daemon.sample_hook = saved
        service.close()
        if tmp is not None:
            tmp.cleanup()
    rep = _report(done, busy, daemon.loop.spin_margin_ns, daemon.hook_ns)
    rep["publisher"] = "process" if cfg.telemetry.process else "thread"
    rep["aa"] = aa
    rep["flush_max_us"] = max(rep["flush_max_us"], pub.flush_ns_max / 1e3)  # a child's: at close
    # the run's totals once the publisher closed: every row the hook wrote (in the "on"
    # windows and the settling after them) either reached the recording or was dropped
    rep["accepted"], rep["published"], rep["dropped"] = (
        pub.ring.accepted, pub.published, pub.ring.dropped)
    return rep


def format_report(r: dict[str, Any]) -> str:
    """A few lines for the terminal."""
    header = (f"{'telemetry':>9} {'cycles':>7} {'compute p50':>11} {'p99':>8} {'max':>8} "
              f"{'latency p50':>11} {'p99':>8} {'max':>8} {'missed':>6}  [us]")
    lines = [header]
    for key in ("off", "on"):
        s = r[key]
        lines.append(f"{key:>9} {s['cycles']:>7} {s['compute_p50_us']:>11.1f} "
                     f"{s['compute_p99_us']:>8.1f} {s['compute_max_us']:>8.1f} "
                     f"{s['latency_p50_us']:>11.1f} {s['latency_p99_us']:>8.1f} "
                     f"{s['latency_max_us']:>8.1f} {s['missed']:>6}")
    if "compute_p99_growth_pair_median" in r:
        lines.append(f"compute p99 growth within each off/on window pair: median "
                     f"{100 * r['compute_p99_growth_pair_median']:+.1f} % over "
                     f"{len(r['compute_p99_growth_pairs'])} pairs")
    lines.append(f"compute p99 growth with telemetry: {100 * r['compute_p99_growth']:+.1f} %; "
                 f"published {r['published']} samples, dropped {r['dropped']}, "
                 f"longest flush {r['flush_max_us']:.0f} us ({r['phases']} alternating phases)")
    ci = r.get("interval") or {}
    if ci:
        g_lo, g_hi = ci["compute_p99_growth_ci"]
        m_lo, m_hi = ci["extra_misses_per_1e5_ci"]
        pct = round(100 * ci["confidence"])
        lines.append(f"{pct} % confidence intervals (bootstrap over {ci['pairs']} window "
                     f"pairs): compute p99 growth {100 * g_lo:+.1f} .. {100 * g_hi:+.1f} %, "
                     f"extra misses {m_lo:+.1f} .. {m_hi:+.1f} per 10^5 cycles")
    if "hook_p99_us" in r:
        lines.append(f"the loop's own telemetry work (the hook: write the row): p50 {r['hook_p50_us']:.1f} "
                     f"us, p99 {r['hook_p99_us']:.1f} us per cycle")
    if r.get("misses_overlapping_publisher_on") is not None:
        lines.append(f"late cycles overlapping the publisher's work: "
                     f"{r['misses_overlapping_publisher_on']} of {r['misses_on']} (on), "
                     f"{r['misses_overlapping_publisher_off']} of {r['misses_off']} (off)")
    return "\n".join(lines)


GROWTH_TARGET = 0.10
"""The telemetry target: loop compute p99 grows by less than this fraction."""


def verdict(r: dict[str, Any]) -> str:
    """The telemetry targets, judged on the confidence intervals: compute p99 growth <
    10 % (met when the whole interval is below), no missed deadlines caused by telemetry
    (none shown while the extra-miss interval reaches down to 0)."""
    ci = r.get("interval") or {}
    if not ci:
        return "telemetry targets: too few window pairs to judge"
    pct = round(100 * ci["confidence"])
    g_lo, g_hi = ci["compute_p99_growth_ci"]
    if g_hi < GROWTH_TARGET:
        g = f"met (the {pct} % CI ends at {100 * g_hi:+.1f} %)"
    elif g_lo >= GROWTH_TARGET:
        g = f"NOT met (the {pct} % CI starts at {100 * g_lo:+.1f} %)"
    else:
        g = f"undecided (the {pct} % CI, {100 * g_lo:+.1f} .. {100 * g_hi:+.1f} %, spans it)"
    m_lo, _ = ci["extra_misses_per_1e5_ci"]
    m = ("none shown (the CI of the extra misses reaches 0)" if m_lo <= 0 else
         f"telemetry adds misses (the {pct} % CI starts at {m_lo:+.1f} per 10^5 cycles)")
    aa = " [A/A check: both should hold]" if r.get("aa") else ""
    return (f"target telemetry compute p99 growth < {100 * GROWTH_TARGET:g} %: {g}\n"
            f"target no missed deadlines caused by telemetry: {m}{aa}")
