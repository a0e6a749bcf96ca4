"""A helper child process of the daemon (telemetry, the ROS 2 bridge): spawned, its
logging set up like the parent's, and waited for until it reports ready.

The child runs ``target(conn, *args, **kwargs)`` and sends ``("ready", ...)`` on
``conn`` once it serves, or ``("error", message)``.  Its log events come out in the
parent's format on the stdout they share (JSON lines off a terminal, console lines on
one): a ``spawn`` child starts with structlog's defaults otherwise.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any


def with_logging(log_setup: tuple[str, bool | None], target: Callable[..., Any], *args: Any,
                 **kwargs: Any) -> Any:
    """A ``spawn`` child's entry: logging set up as ``log_setup`` (the parent's
    :data:`mmctl.runtime.logging.CURRENT`), then ``target(*args, **kwargs)``."""
    from mmctl.runtime.logging import setup_logging

    setup_logging(log_setup[0], json=log_setup[1])
    return target(*args, **kwargs)


def spawn_ready(target: Callable[..., Any], args: tuple[Any, ...], *, name: str,
                who: str, start_timeout: float, error: type[Exception],
                kwargs: dict[str, Any] | None = None) -> tuple[Any, Connection]:
    """Start ``target(conn, *args, **kwargs)`` in a ``spawn`` child called ``name`` and
    wait up to ``start_timeout`` [s] for its ``("ready", ...)``.

    Returns (process, the parent's end of the pipe).  Silence, an early exit or an
    ``("error", message)`` reply end the child and raise ``error`` naming ``who``.
    """
    from mmctl.runtime import logging as mmctl_logging

    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=with_logging, args=(mmctl_logging.CURRENT, target, child, *args),
                       kwargs=kwargs or {}, name=name, daemon=True)
    try:
        proc.start()
        child.close()
        try:
            if not parent.poll(start_timeout):
                raise error(f"{who} did not start within {start_timeout:g} s")
            reply = parent.recv()
        except (EOFError, OSError) as exc:
            raise error(f"{who} exited at start (code {proc.exitcode})") from exc
        if reply[0] != "ready":
            raise error(f"{who}: {reply[1] if len(reply) > 1 else reply}")
    except BaseException:
        if proc.is_alive():
            proc.kill()
            proc.join(5.0)
        parent.close()
        raise
    return proc, parent
