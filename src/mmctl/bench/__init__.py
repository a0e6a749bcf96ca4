"""Benchmarks that print figures (`mmctl bench idk|loop`, `tools/`): timing the control
chain and the daemon's loop, and the statistics that compare them.  The daemon never
imports this package; `tests/test_layers.py` holds it to that."""
