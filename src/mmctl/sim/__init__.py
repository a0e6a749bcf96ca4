"""Simulation: fakes that speak the real protocols, the simulated plant and the simulated human."""
