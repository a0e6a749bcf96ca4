"""The runtime around the pure control chain: fixed-period loop, timing ring, safety
state machine, daemon composition, control socket, systemd notify and logging."""
