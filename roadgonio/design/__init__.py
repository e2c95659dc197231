"""Instrument design: sweeps of instrument parameters, tolerance maps, the Pareto front of signal
against |k_A - 1| and the best design (issue 12). Builds on :mod:`roadgonio.engines`."""
