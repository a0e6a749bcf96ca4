"""Live telemetry and trial recordings (rerun).

The loop thread hands one :class:`~mmctl.telemetry.sample.TelemetrySample` per cycle to
a bounded, never-blocking queue; a publisher thread batches the samples to rerun (a
spawned viewer, a running viewer, an ``.rrd`` file).  Nothing here imports rerun at
module import time: with telemetry off, rerun is never loaded.

Modules: ``sample`` (the per-cycle value), ``queue`` (bounded drop-counting queue),
``batch`` (samples -> columns), ``publisher`` (the thread), ``layout`` (entity paths and
the blueprint), ``scene`` (3-D robot drawing), ``rerun_sink`` (the only module that talks
to rerun when logging), ``recording`` (read an ``.rrd`` back), ``trial`` (bracketing and
the paper's metrics).
"""
