"""Benchmarks (``make bench`` / ``safemimic bench``): each writes JSON under bench/results/."""
