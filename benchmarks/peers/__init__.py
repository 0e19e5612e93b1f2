"""Peers of the project's simulator for ``bench_sim.py``: the shared problem and one script per peer."""
