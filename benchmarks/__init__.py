"""Benchmarks of kohpymc against reference samplers (``make bench``)."""
