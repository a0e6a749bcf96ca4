"""One ForceSensor contract, run against both transports and their protocol fakes.

The real client code (``open_sensor``) talks to the simulated sensors over the real wire
protocols: python-can's ``virtual`` bus for CAN, UDP on 127.0.0.1 for RDT.
"""

from __future__ import annotations

import dataclasses
import itertools
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from mmctl.config import default_config
from mmctl.errors import FaultCause, ProtocolError, SafetyFault, TransportError
from mmctl.sim.fake_ft_can import (
    STATUS_BUS_ERROR,
    STATUS_DAC_ADC_TOO_HIGH,
    STATUS_DAC_ADC_TOO_LOW,
    STATUS_SATURATION,
    STATUS_WATCHDOG_RESET,
    FakeFtCanSensor,
)
from mmctl.sim.fake_rdt import STATUS_ERROR, FakeRdtServer
from mmctl.sim.fake_rdt import STATUS_SATURATION as RDT_SATURATION
from mmctl.sim.wrench_source import CallableWrench
from mmctl.transports.sensor import ForceSensor, open_sensor

WAIT = 10.0  # upper bound for waiting on an event (never reached when things work)
W0 = np.array([3.5, -7.25, 42.0, 0.4, -0.3, 1.2])
_names = itertools.count()


class Rig:
    """A running fake plus a factory for clients pointed at it."""

    def __init__(self, transport: str):
        self.transport = transport
        self.value = W0.copy()
        source = CallableWrench(lambda t: self.value)
        cfg = default_config().sensor
        if transport == "can":
            ch = f"test-contract-{next(_names)}"
            self.fake: Any = FakeFtCanSensor(source, channel=ch).start()
            self.cfg = dataclasses.replace(
                cfg, transport="can", can=dataclasses.replace(cfg.can, interface="virtual",
                                                              channel=ch, timeout=0.02))
            self.bound = self.fake.quantisation_bound()
            self.status = {"error": STATUS_BUS_ERROR, "saturation": STATUS_SATURATION}
        else:
            self.fake = FakeRdtServer(source, rate_hz=1000.0).start()
            host, port = self.fake.address
            self.cfg = dataclasses.replace(
                cfg, transport="rdt", rdt=dataclasses.replace(cfg.rdt, host=host, port=port))
            self.bound = np.full(6, 0.5e-6)
            self.status = {"error": STATUS_ERROR, "saturation": RDT_SATURATION}

    def sensor(self, stale_timeout: float = 5.0) -> ForceSensor:
        wrench = dataclasses.replace(self.cfg.wrench, stale_timeout=stale_timeout)
        return open_sensor(dataclasses.replace(self.cfg, wrench=wrench))


@pytest.fixture(params=["can", "rdt"])
def rig(request: pytest.FixtureRequest) -> Iterator[Rig]:
    r = Rig(request.param)
    yield r
    r.fake.stop()


def fresh_samples(sensor: ForceSensor, n: int) -> list:
    out: list = []
    seq = None
    deadline = time.monotonic() + WAIT
    while len(out) < n:
        assert time.monotonic() < deadline, f"only {len(out)}/{n} fresh samples"
        w = sensor.read()
        if w.sequence != seq:
            seq = w.sequence
            out.append(w)
        else:
            time.sleep(0.0005)
    return out


def read_until_raises(sensor: ForceSensor) -> int:
    """Read until an exception escapes; returns the number of reads (for figures)."""
    deadline = time.monotonic() + WAIT
    n = 0
    while time.monotonic() < deadline:
        sensor.read()
        n += 1
        time.sleep(0.0005)
    raise AssertionError(f"no error in {n} reads")


def test_open_sensor_gives_a_force_sensor(rig: Rig) -> None:
    sensor = rig.sensor()
    assert isinstance(sensor, ForceSensor)
    with pytest.raises(TransportError, match="not connected"):
        sensor.read()


def test_reads_the_source_wrench_through_the_calibration(rig: Rig) -> None:
    with rig.sensor() as sensor:
        samples = fresh_samples(sensor, 20)
    for w in samples:
        assert np.all(np.isfinite(w.as_array()))
        err = np.abs(w.as_array() - W0)
        assert np.all(err <= rig.bound + 1e-12), (err, rig.bound)
    seqs = [w.sequence for w in samples]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    stamps = [w.timestamp for w in samples]
    assert stamps == sorted(stamps)
    if rig.transport == "can":
        # without the (non-identity) matrix the same gauges would read far off
        naive = rig.fake.gauges_for(W0) / np.array([30] * 3 + [1000] * 3)
        assert np.max(np.abs(naive - W0)) > 20 * np.max(rig.bound)


def test_close_twice_is_fine(rig: Rig) -> None:
    sensor = rig.sensor()
    sensor.connect()
    sensor.connect()  # no-op when connected
    sensor.read()
    sensor.close()
    sensor.close()
    with pytest.raises(TransportError):
        sensor.read()


def test_silent_sensor_becomes_stale(rig: Rig) -> None:
    stale = 0.05
    with rig.sensor(stale_timeout=stale) as sensor:
        fresh_samples(sensor, 3)
        rig.fake.silent = True
        t0 = time.monotonic()
        with pytest.raises(SafetyFault) as info:
            read_until_raises(sensor)
        elapsed = time.monotonic() - t0
    assert info.value.cause is FaultCause.SENSOR_STALE
    # age > stale_timeout raised it; the detail is rounded to 0.01 ms (50.004 -> 50.0)
    assert info.value.details["age_ms"] >= stale * 1e3
    print(f"{rig.transport}: stale reported {elapsed * 1e3:.1f} ms after the sensor went silent")


@pytest.mark.parametrize(("kind", "cause"), [("error", FaultCause.SENSOR_STATUS),
                                             ("saturation", FaultCause.SENSOR_SATURATION)])
def test_status_bits_fault(rig: Rig, kind: str, cause: FaultCause) -> None:
    with rig.sensor() as sensor:
        fresh_samples(sensor, 2)
        rig.fake.status = rig.status[kind]
        with pytest.raises(SafetyFault) as info:
            read_until_raises(sensor)
        assert info.value.cause is cause
        rig.fake.status = 0  # the fault is a condition, not a latch: healthy again
        # (records sent before the flip may still be queued -- many, on a busy machine:
        # a read drains what is queued, so a few more reads may see the bit; a latch
        # would see it on every read)
        for _ in range(50):
            try:
                fresh_samples(sensor, 2)
                break
            except SafetyFault as exc:
                assert exc.cause is cause
        else:
            raise AssertionError(f"still {cause.value} 50 reads after the device cleared it")


@pytest.mark.parametrize(
    ("bit", "names"),
    [(STATUS_DAC_ADC_TOO_HIGH, ["dac_adc_check_too_high", "any_error"]),
     (STATUS_DAC_ADC_TOO_LOW, ["dac_adc_check_too_low", "any_error"]),
     (STATUS_WATCHDOG_RESET, ["watchdog_reset", "any_error"]),
     (STATUS_BUS_ERROR, ["can_bus_error", "any_error"])],
)
def test_can_status_bits_are_a_status_fault_naming_each_bit(bit: int, names: list[str]) -> None:
    """The Axia80's DAC/ADC self-check, watchdog reset and bus error (ATI's status word)
    reach the daemon as SENSOR_STATUS with each set bit named, never as saturation."""
    rig = Rig("can")
    try:
        with rig.sensor() as sensor:
            fresh_samples(sensor, 2)
            rig.fake.status = bit
            with pytest.raises(SafetyFault) as info:
                read_until_raises(sensor)
            assert info.value.cause is FaultCause.SENSOR_STATUS
            assert info.value.details["bits"] == names
            rig.fake.status = 0
            fresh_samples(sensor, 2)
    finally:
        rig.fake.stop()


def test_garbage_is_a_protocol_error(rig: Rig) -> None:
    with rig.sensor() as sensor:
        fresh_samples(sensor, 2)
        rig.fake.garbage = True
        with pytest.raises(ProtocolError):
            read_until_raises(sensor)


def test_nothing_answers_on_connect(rig: Rig) -> None:
    rig.fake.stop()
    cfg = rig.cfg
    if rig.transport == "can":
        cfg = dataclasses.replace(cfg, can=dataclasses.replace(
            cfg.can, channel="test-contract-nobody", connect_timeout=0.05))
    sensor = open_sensor(cfg)
    with pytest.raises(TransportError, match="nothing answers|no reply"):
        sensor.connect()
    sensor.close()
