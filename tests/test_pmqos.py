"""PM QoS CPU-latency request: what is written, held and withdrawn; the real device
when this machine lets us write it."""

from __future__ import annotations

import os
import struct
from pathlib import Path

import pytest

from mmctl.config import ConfigError, config_from_dict
from mmctl.runtime.pmqos import DEVICE, CpuLatencyRequest, current_limit


def test_request_writes_int32_and_holds_until_release(tmp_path: Path) -> None:
    dev = tmp_path / "cpu_dma_latency"
    dev.write_bytes(b"")
    req = CpuLatencyRequest(25, path=dev)
    assert not req.held and dev.read_bytes() == b""  # no I/O before acquire
    assert req.acquire() and req.held
    assert req.acquire()  # twice: still one request
    assert struct.unpack("=i", dev.read_bytes()) == (25,)
    req.release()
    req.release()  # idempotent
    assert not req.held
    with CpuLatencyRequest(0, path=dev) as held:
        assert held.held
    assert not held.held


def test_missing_device_is_a_warning_not_an_error(tmp_path: Path) -> None:
    req = CpuLatencyRequest(0, path=tmp_path / "absent")
    assert req.acquire() is False
    assert not req.held
    assert current_limit(tmp_path / "absent") is None


@pytest.mark.parametrize("us", [-1, 2_000_001])
def test_out_of_range_value_is_refused(us: int) -> None:
    with pytest.raises(ValueError, match="us must be in"):
        CpuLatencyRequest(us)


def test_config_names_key_and_range() -> None:
    with pytest.raises(ConfigError) as info:
        config_from_dict({"loop": {"cpu_dma_latency": -2}}, "x.yaml")
    assert info.value.key == "loop.cpu_dma_latency"
    assert ">= -1" in str(info.value)
    assert config_from_dict({}, "x.yaml").loop.cpu_dma_latency == -1  # off by default


@pytest.mark.skipif(not os.access(DEVICE, os.W_OK), reason="no write access to the device")
def test_real_device_limit_while_held() -> None:
    before = current_limit()
    assert before is not None
    if before <= 777:
        pytest.skip(f"another process already holds a tighter request ({before} us)")
    with CpuLatencyRequest(777):
        assert current_limit() == 777
    assert current_limit() > 777  # withdrawn (a looser request may be held by another test)
