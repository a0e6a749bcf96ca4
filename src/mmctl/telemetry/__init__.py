"""Live telemetry and trial recordings (rerun).

The loop thread writes one row per cycle into a bounded, never-blocking ring
(:mod:`~mmctl.telemetry.ring`); a publisher batches the rows to rerun (a spawned viewer,
a running viewer, an ``.rrd`` file), in a child process that maps the ring from shared
memory (``telemetry.process``, the default) or in a thread of the daemon.  Nothing here
imports rerun at module import time: with telemetry off, rerun is never loaded.

Modules: ``sample`` (the per-cycle value), ``ring`` (its row layout and the shared
ring), ``queue`` (bounded drop-counting queue, for events), ``batch`` (rows -> columns),
``publisher`` (the batching loop), ``process_publisher`` (it, in a child process),
``layout`` (entity paths and the blueprint), ``scene`` (3-D robot drawing),
``rerun_sink`` (the only module that talks to rerun when logging), ``recording`` (read
an ``.rrd`` back), ``trial`` (bracketing and the paper's metrics).
"""
