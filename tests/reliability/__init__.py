"""The reliability checks, one test each: watchdogs, rate limits, kill -9 faults, fuzzed input, load."""
