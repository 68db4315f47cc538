"""``make bench`` / ``python -m bench.run`` (from the checkout): run benchmarks, print a table, write JSON per benchmark."""

from __future__ import annotations

import argparse
import importlib
import json
import time
from pathlib import Path

from bench.common import RESULTS_DIR, write_result
from tests.support.machine import machine
from bench.report import render, verdicts

#: benchmark name → module with ``run(**kwargs) -> dict`` (later issues add safety_step, latency, ...).
BENCHMARKS: dict[str, str] = {
    "codec": "bench.codec",
    "perception": "bench.perception",
    "safety_step": "bench.safety_step",
    "geometry": "bench.geometry",
    "latency": "bench.latency",
    "point_filter": "bench.point_filter",
    "angle_rates": "bench.angle_rates",
    "human_update": "bench.human_update",
}


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="python -m bench.run")
    parser.description = "Run benchmarks; each writes OUT/<name>.json with name, p50, p99, unit and the machine."
    parser.add_argument("names", nargs="*", choices=[[], *BENCHMARKS], metavar="NAME", help=f"benchmarks to run (default: all of {', '.join(BENCHMARKS)})")
    parser.add_argument("--out", type=Path, default=RESULTS_DIR, help="result folder (default: bench/results)")
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write all results into one JSON file")
    parser.add_argument("--docs", type=Path, metavar="FILE", help="also write a Markdown report of this run (make bench: docs/benchmarks.md)")
    return parser


def run(args: argparse.Namespace) -> int:
    results = []
    for name in args.names or list(BENCHMARKS):
        print(f"running {name} ...", flush=True)
        module = importlib.import_module(BENCHMARKS[name])
        result = module.run()
        path = getattr(module, "write", write_result)(result, args.out)  # a module may write its own files
        results.append(result)
        print(f"  wrote {path}")
    print(f"\n{'benchmark':<16}{'p50':>12}{'p99':>12}  unit  budget")
    for r in results:
        checks = verdicts(r)  # budget_p50 / budget_p99, or with the unit (budget_p99_ms)
        verdict = " ".join(("ok" if ok else "OVER") + f" ({key} ≤ {budget})" for key, _, budget, ok in checks)
        print(f"{r['name']:<16}{r['p50']:>12.2f}{r['p99']:>12.2f}  {r['unit']:<4}  {verdict}")
    if args.docs:
        args.docs.parent.mkdir(parents=True, exist_ok=True)
        args.docs.write_text(render(results, machine(), time.strftime("%Y-%m-%d %H:%M:%S %z")))
        print(f"  wrote {args.docs}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(run(build_parser().parse_args()))
