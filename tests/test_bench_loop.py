"""`mmctl bench loop --json` on the simulated robot: the documented keys, figures that
are numbers, telemetry windows when asked.  Nothing about speed is asserted."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from mmctl.bench.telemetry_overhead import MIN_PAIRS
from mmctl.cli import main
from mmctl.runtime.pmqos import DEVICE, current_limit
from simconfig import LOAD_PROOF, write_sim_config

KEYS = {"compute_p50_us", "compute_p99_us", "compute_max_us", "latency_p50_us",
        "latency_p99_us", "latency_p999_us", "miss_rate", "cycles"}


@pytest.mark.timeout(600)  # (300 s ran out once with the machine at load 12)
@pytest.mark.parametrize("process", [True, False], ids=["child-process", "thread"])
def test_bench_loop_json(tmp_path: Path, loopback_host: str, process: bool,
                         capsys: pytest.CaptureFixture[str]) -> None:
    # the load-proof budgets: on a busy machine a stale device would fault the daemon,
    # and a faulted cycle has no sample for the telemetry windows to publish
    path = write_sim_config(loopback_host, tmp_path,
                            {**LOAD_PROOF, "telemetry": {"process": process}}, "bench.yaml")
    rc = main(["bench", "loop", "--seconds", "1", "--json", "--telemetry", "--config", str(path),
               "--host", loopback_host, "--cpu-dma-latency", "1500", "--telemetry-seconds", "2",
               "--telemetry-windows", "5", "--latency-steps", "4" if process else "0",
               *(["--ros2-ab", "2"] if process else ["--collision-ab", "4"])])
    out, err = capsys.readouterr()
    assert rc == 0, err[-3000:]
    rep = json.loads(out)
    # the daemon held the PM QoS request for the run (where this machine allows it) and
    # withdrew it at shutdown
    assert rep["cpu_dma_latency_us"] == (1500 if os.access(DEVICE, os.W_OK) else None)
    assert current_limit() != 1500  # (another test's request may be in force meanwhile)
    assert rep["windows"] == 10
    for key in ("loop", "sleep_baseline"):
        fig = rep[key]
        assert KEYS <= set(fig), key
        # about 500 cycles in 1 s quiet; with both cores busy (two `yes` loops) the bench
        # counted 41-200 (the same before and after the re-cut): the loop ran, no more
        assert fig["cycles"] > 10
        assert 0.0 <= fig["miss_rate"] <= 1.0
        assert 0.0 < fig["compute_p50_us"] <= fig["compute_p99_us"] <= fig["compute_max_us"]
        assert fig["latency_p50_us"] <= fig["latency_p99_us"] <= fig["latency_p999_us"]
    tel = rep["telemetry"]
    assert rep["telemetry_seconds"] == 2.0
    assert tel["phases"] == 10 and tel["off"]["cycles"] > 0 and tel["on"]["cycles"] > 0
    # the bootstrap over the 5 window pairs that both held cycles: a 0.2-s window of a
    # starved loop can hold none (seen with both cores busy); below MIN_PAIRS, none
    usable = len(tel.get("compute_p99_growth_pairs", []))
    assert usable <= 5
    ci = tel["interval"]
    if usable >= MIN_PAIRS:
        assert ci["pairs"] == usable and ci["confidence"] == 0.95
        for key in ("compute_p99_growth_ci", "extra_misses_per_1e5_ci"):
            assert ci[key][0] <= ci[key][1], key
    else:
        assert ci == {}, ci
    # the "on" windows' samples reached the recording (a faulted daemon has none: say so)
    assert tel["published"] > 0, (tel, rep.get("faults"), rep["loop"].get("armed_at_end"))
    assert tel["published"] + tel["dropped"] == tel["accepted"]
    assert tel["publisher"] == ("process" if process else "thread")
    assert 0.0 < tel["hook_p50_us"] <= tel["hook_p99_us"]  # the hook ran in the "on" windows
    if process:  # the publisher never holds the loop's interpreter: nothing to attribute
        assert tel["misses_overlapping_publisher_on"] is None
        assert tel["misses_overlapping_publisher_off"] is None
    else:
        assert 0 <= tel["misses_overlapping_publisher_on"] <= tel["misses_on"]
        assert 0 <= tel["misses_overlapping_publisher_off"] <= tel["misses_off"]
    assert rep["targets"]["compute_p99_us"] == 300.0
    assert 0.0 < rep["idk_step"]["p50_us"] <= rep["idk_step"]["p99_us"]
    if process:  # force-to-command: each push step answered by a speedJ, after its sample
        f2c = rep["force_to_command"]
        assert f2c["steps"] == 4, f2c
        if rep["faults"] == 0:  # (a fault a loaded machine causes disarms: no answers)
            assert f2c["arm_responses"] >= 3, f2c
            assert 0.0 < f2c["force_to_speedj_p50_us"] <= f2c["force_to_command_p99_us"]
    else:
        assert "force_to_command" not in rep
    assert rep["faults"] >= 0 and isinstance(rep["faults"], int)
    if not process:  # the self-collision check on vs off, 4 pairs of 0.5 s windows
        ab = rep["collision_check"]
        assert ab["pairs"] == 4 and ab["seconds"] == 4.0 and ab["faults"] >= 0
        for key in ("on", "off"):
            assert KEYS <= set(ab[key]) and ab[key]["cycles"] > 10, key
    else:  # the ROS 2 bridge fed and not (its child on loopback only), 4 pairs of 0.25 s
        assert "collision_check" not in rep
        ros = rep["ros2"]
        # the loop fed the bridge's ring in the "on" windows; the child (SCHED_IDLE) may
        # take none of it while both cores are busy (seen with two `yes` loops)
        assert ros["pairs"] == 4 and ros["faults"] >= 0 and ros["rows_fed"] > 0
        assert 0 <= ros["rows_taken"] <= ros["rows_fed"] + 4096
        for key in ("on", "off"):
            assert KEYS <= set(ros[key]) and ros[key]["bridge_cpu_percent"] >= 0.0, key


def test_a_fault_during_the_run_is_flagged() -> None:
    from mmctl.bench.loop import fault_warning

    assert fault_warning({"faults": 0}) is None
    text = fault_warning({"faults": 2})
    assert text is not None and text.startswith("WARNING: the robot faulted 2 time(s)")
    assert "disarmed loop" in text


def test_verdict_names_each_target_met_or_not_and_against_sleep() -> None:
    from mmctl.bench.loop import TARGETS, verdict

    loop = {"compute_p99_us": 541.0, "latency_p99_us": 14.0, "miss_rate": 0.001}
    sleep = {"compute_p99_us": 626.0, "latency_p99_us": 76.0, "miss_rate": 0.0009}
    lines = verdict({"targets": TARGETS, "loop": loop, "sleep_baseline": sleep}).splitlines()
    assert lines == [
        "target compute p99 < 300 us: 541 us, NOT met; better than the time.sleep wait (626 us)",
        "target wake latency p99 < 50 us: 14 us, met; better than the time.sleep wait (76 us)",
        ("target miss rate < 0.05 %: 0.1 %, NOT met; not better than the time.sleep wait "
         "(0.09 %)"),
    ]
    loop["step_p50_us"] = 120.0
    lines = verdict({"targets": TARGETS, "loop": loop, "sleep_baseline": sleep,
                     "step_ratio_p50": 1.5, "idk_step": {"p50_us": 80.0},
                     "force_to_command": {"force_to_command_p99_us": 1500.0}}).splitlines()
    assert lines[3:] == [
        "target daemon step p50 < 1.25 x back-to-back step p50: x1.50 (120 vs 80 us), NOT met",
        "target force-to-command p99 < 2000 us: 1500 us, met",
    ]


@pytest.mark.parametrize("text", ["one", "1;2", "-1"])
def test_a_bad_cpu_list_is_refused_naming_the_value(text: str,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["bench", "loop", f"--cpu-affinity={text}"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--cpu-affinity" in err and repr(text) in err


@pytest.mark.parametrize("flag", ["--seconds", "--telemetry-seconds", "--collision-ab"])
def test_a_non_positive_duration_is_refused_naming_the_flag(
        flag: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "loop", "--telemetry", flag, "0"]) != 0
    assert f"{flag} 0: must be > 0" in capsys.readouterr().err


def test_bench_startup_bins_misses_from_each_event_and_finds_when_they_settle() -> None:
    """`mmctl bench startup`'s figures from a made-up run: 500 Hz, misses only in the
    first second after the enable; steady (the 2 s before the fault) without any."""
    import argparse

    import numpy as np

    from mmctl.bench.startup import _figures

    period = 2_000_000
    deadline = np.arange(0, 30 * 500) * period  # 30 s of cycles
    missed = np.zeros_like(deadline)
    at = {"start": 0, "enable": 10 * 10**9, "fault": 20 * 10**9, "re-enable": 22 * 10**9,
          "end": 30 * 10**9}
    first_second = (deadline >= at["enable"]) & (deadline < at["enable"] + 10**9)
    missed[first_second & (np.arange(len(deadline)) % 2 == 0)] = 1  # every other cycle
    args = argparse.Namespace(bin=0.5, steady=2.0, after=8.0, fault="drive_fault")
    out = _figures(deadline, missed, at, args, faults=1)
    assert out["steady_pct"] == 0.0 and out["settled_bound_pct"] == 0.5
    enable = out["events"]["enable"]
    assert [b["miss_pct"] for b in enable["bins"][:3]] == [
        round(100 * 125 / 375, 2), round(100 * 125 / 375, 2), 0.0]
    assert enable["settled_after_s"] == 1.0
    assert out["events"]["start"]["settled_after_s"] == 0.0
    assert out["events"]["re-enable"]["first_2s_pct"] == 0.0
