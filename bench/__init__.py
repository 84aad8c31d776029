"""Benchmarks behind `sim2act bench`: speed targets live here, not in timed tests."""
