"""``safemimic reliability`` / ``make reliability``: run the reliability checks, write the report.

Writes ``bench/results/reliability.json``: ``{"checks": [{"name", "passed", figures...}],
"passed", "duration_s", "machine", "time"}``; exits 1 if any check failed.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import time
from pathlib import Path

from bench.common import RESULTS_DIR, machine
from bench.reliability import CheckResult

#: check group → module with ``run(quick: bool) -> list[CheckResult]``.
GROUPS: dict[str, str] = {
    "watchdogs": "bench.reliability.watchdogs",
    "load": "bench.reliability.load",
    "faults": "bench.reliability.faults",
    "fuzz": "bench.reliability.fuzz",
}


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic reliability")
    parser.description = (
        "Run the reliability checks (watchdogs, rate limits, kill -9 faults, fuzzed input, load) "
        "and write OUT/reliability.json; exit 1 if any check failed. The full run takes under 10 minutes."
    )
    parser.add_argument("groups", nargs="*", choices=[[], *GROUPS], metavar="GROUP",
                        help=f"check groups to run (default: all of {', '.join(GROUPS)})")
    parser.add_argument("--quick", action="store_true", help="the bounded variant make test runs (seconds per group)")
    parser.add_argument("--out", type=Path, default=RESULTS_DIR, help="result folder (default: bench/results)")
    return parser


def run_groups(groups: list[str], quick: bool) -> list[CheckResult]:
    """Run the named groups in order, printing each result as it comes."""
    results: list[CheckResult] = []
    for group in groups:
        print(f"[{group}] running{' (quick)' if quick else ''} ...", flush=True)
        started = time.monotonic()
        for result in importlib.import_module(GROUPS[group]).run(quick=quick):
            print(f"  {result}", flush=True)
            results.append(result)
        print(f"[{group}] {time.monotonic() - started:.1f} s", flush=True)
    return results


def run(args: argparse.Namespace) -> int:
    started = time.monotonic()
    results = run_groups(args.groups or list(GROUPS), args.quick)
    passed = all(r.passed for r in results) and bool(results)
    report = {
        "checks": [r.to_json() for r in results],
        "passed": passed,
        "quick": args.quick,
        "duration_s": round(time.monotonic() - started, 1),
        "machine": machine(),
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "reliability.json"
    path.write_text(json.dumps(report, indent=2) + "\n")
    failed = [r.name for r in results if not r.passed]
    print(f"\n{len(results) - len(failed)}/{len(results)} checks passed in {report['duration_s']} s; wrote {path}")
    if failed:
        print("failed: " + ", ".join(failed), file=sys.stderr)
    return 0 if passed else 1


if __name__ == "__main__":
    raise SystemExit(run(build_parser().parse_args()))
