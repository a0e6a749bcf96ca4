"""Pure control math: no I/O, no clocks, no logging (numpy + Pinocchio)."""
