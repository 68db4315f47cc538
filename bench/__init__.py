"""Benchmarks (``make bench`` / ``python -m bench.run`` in the checkout, not installed): each writes JSON under bench/results/."""
