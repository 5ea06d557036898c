"""Benchmarks over the simulator: :mod:`decod_rs.bench.matrix` runs the generalisation
matrix (every scene x sensor that sees its walls x return mode x seed x drift profile, plus
geometry and speed variants, some held out of tuning) and writes ``matrix.md`` and
``matrix.json``."""
