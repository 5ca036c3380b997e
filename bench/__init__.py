"""Benchmarks: `make bench` prints figures (timings, throughputs); no pass/fail."""
