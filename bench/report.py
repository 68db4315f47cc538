"""docs/benchmarks.md from one ``make bench`` run: every figure comes from that run's JSON.

Only ratios within this one run compare fairly: the machine is shared (its load average is
written next to the figures), so absolute times move from run to run.
"""

from __future__ import annotations

from typing import Any

_PREAMBLE = """# Benchmarks

Written by `make bench` (`python -m bench.run --docs docs/benchmarks.md`, `bench/report.py`) from the
JSON of one run (`bench/results/*.json`, not committed). Every number below was measured in that
run on the machine named here, except figures marked **external** (their source is named). The
machine is shared with other jobs: compare the ratios within this run, not absolute times across
runs.
"""


def _f(value: float | None, digits: int = 3) -> str:
    if value is None:
        return "–"
    if abs(value) >= 100:
        return f"{value:,.0f}"
    return f"{value:.{digits}g}" if abs(value) < 1 else f"{value:.{digits}f}".rstrip("0").rstrip(".")


def verdicts(result: dict[str, Any]) -> list[tuple[str, float, float, bool]]:
    """(key, value, budget, within) of every budget a result states: ``budget_p50``/``budget_p99``
    or with the unit (``budget_p99_ms``)."""
    out = []
    for key in ("p50", "p99"):
        for budget_key in (f"budget_{key}", f"budget_{key}_{result.get('unit', '')}"):
            if budget_key in result:
                out.append((key, float(result[key]), float(result[budget_key]), float(result[key]) <= float(result[budget_key])))
                break
    return out


def render(results: list[dict[str, Any]], machine: dict[str, Any], date: str) -> str:
    lines = [_PREAMBLE]
    load = machine.get("load_avg")
    lines += [
        "## Machine and date",
        "",
        f"- date: {date}",
        f"- CPU: {machine.get('cpu')}, {machine.get('cores')} cores",
        f"- load average (1, 5, 15 min) at the end of the run: {', '.join(f'{x:.2f}' for x in load) if load else 'unknown'}",
        f"- Python {machine.get('python')}, {machine.get('platform')}",
        "",
        "## Every benchmark",
        "",
        "| benchmark | p50 | p99 | unit | budget |",
        "|---|---|---|---|---|",
    ]
    for r in results:
        budget = ", ".join(f"{k} ≤ {_f(b)} {'ok' if ok else '**OVER**'}" for k, _, b, ok in verdicts(r)) or ""
        lines.append(f"| {r['name']} | {_f(r['p50'])} | {_f(r['p99'])} | {r['unit']} | {budget} |")
    lines.append("")
    for r in results:
        if r["name"] == "safety_step":
            lines += safety_section(r)
    return "\n".join(lines).rstrip() + "\n"


def safety_section(r: dict[str, Any]) -> list[str]:
    """The safety step, its floor, mink side by side, DAQP's iterations (bench/safety_step.py)."""
    fl, it, mk = r["floor"], r["daqp_iterations"], r["mink"]
    m8, m8d, m29 = mk["mink8"], mk["mink8_default_detection"], mk["mink29"]
    daqp, osqp = r["backends"]["daqp"], r["backends"]["osqp"]
    load = r.get("load_avg_during", {})
    ext = r["oscbf_external"]
    s400, s126 = r["sized"]["400"], r["sized"]["126"]
    return [
        "## Safety step (`python -m bench.run safety_step`)",
        "",
        f"{r['what']}; {r['timing']}; load average during the timed blocks "
        f"{load.get('before', [0])[0]:.2f} → {load.get('after', [0])[0]:.2f} (1 min).",
        "",
        "| what (same run) | p50 | p99 | note |",
        "|---|---|---|---|",
        f"| our step, {r['constraints']} pair rows, DAQP | {_f(daqp['p50_ms'])} ms | {_f(daqp['p99_ms'])} ms | "
        f"budget {_f(r['budget_p50_ms'])} / {_f(r['budget_p99_ms'])} ms; QP {_f(daqp['qp_share_p50'] * 100, 2)} % of it |",
        f"| same, OSQP | {_f(osqp['p50_ms'])} ms | {_f(osqp['p99_ms'])} ms | |",
        f"| floor: FK + capsule Jacobians alone | {_f(fl['fk_p50_ms'])} ms | | |",
        f"| floor: bare `daqp.solve` alone ({fl['rows']} rows + bounds) | {_f(fl['qp_p50_ms'])} ms | | "
        f"{_f(fl['bare_qp_iterations_mean'])} iterations on average |",
        f"| **step / (FK + QP)** | **{fl['ratio_step_over_floor']:.2f}×** | | goal ≤ {_f(fl['goal_ratio'])}× and p50 ≤ "
        f"{_f(fl['goal_step_p50_ms'])} ms: {'met' if fl['meets_ratio_goal'] and fl['meets_p50_goal'] else 'not met'} |",
        f"| **mink-8**: reduced model (nv {m8['nv']}), same {mk['verification']['mink8']['pairs_mink']} pairs, every pair "
        f"evaluated | {_f(m8['p50_ms'])} ms | {_f(m8['p99_ms'])} ms | ours **{r['speedup_vs_mink8']:.1f}×** faster |",
        f"| mink-29: full model (nv {m29['nv']}), 21 joints locked, same {mk['verification']['mink29']['pairs_mink']} pairs "
        f"| {_f(m29['p50_ms'])} ms | {_f(m29['p99_ms'])} ms | ours {r['speedup_vs_mink29']:.1f}× faster |",
        f"| mink-8 at its default detection distance ({_f(m8d['collision_detection_distance_m'])} m; "
        f"{_f(m8d['rows_evaluated_mean'])} pairs evaluated on average) | {_f(m8d['p50_ms'])} ms | {_f(m8d['p99_ms'])} ms | "
        f"not the same safety: min robot–human clearance {_f(mk['clearance']['mink8_default_detection']['min_human_clearance_m'] * 1000)} mm |",
        f"| our step, 400 rows ({s400['people']} people) | {_f(s400['p50_ms'])} ms | {_f(s400['p99_ms'])} ms | "
        f"{s400['hz_mean']:,.0f} Hz mean; **external**: oscbf ({ext['claim']}; {ext['source']}) |",
        f"| our step, 126 rows | {_f(s126['p50_ms'])} ms | {_f(s126['p99_ms'])} ms | {s126['hz_mean']:,.0f} Hz mean |",
        "",
        f"mink runs `solve_ik` with DAQP at our iteration limit and tolerance ({mk['solver_settings']}), warm start: "
        f"{mk['warm_start']}. The reduced model's links without joints are welded to the world, so mink drops "
        f"{m8['pairs_dropped_by_mink']} pairs (static link × mocap person) as parent–child; the benchmark gives them back "
        f"and checks the pair sets equal ours (same_pair_count: {mk['same_pair_count']}; distances agree to "
        f"{mk['verification']['mink8']['max_distance_diff_m']:.1e} m, gradients to {mk['verification']['mink8']['max_gradient_diff']:.1e}).",
        "",
        "**DAQP iterations per step** (same problems; warm = the previous active set as DAQP `sense` flags, "
        f"{it['flags']}):",
        "",
        "| start | mean | p50 | max |",
        "|---|---|---|---|",
        *(f"| {name.replace('_', ' ')} | {_f(it[name]['mean'])} | {_f(it[name]['p50'])} | {it[name]['max']} |"
          for name in ("warm", "cold", "old_flags")),
        "",
        f"Breakdown of one step (p50, µs, instrumented pass): FK {_f(r['breakdown_us']['fk_p50_us'])}, rows "
        f"{_f(r['breakdown_us']['rows_p50_us'])}, QP call {_f(r['breakdown_us']['qp_call_p50_us'])}, the rest "
        f"{_f(r['breakdown_us']['overhead_p50_us'])}.",
        "",
    ]


def main(argv: list[str] | None = None) -> int:
    """``python -m bench.report [OUT]``: re-render the report from the JSON under bench/results/
    (the figures of the last run; machine and date as that run recorded them)."""
    import argparse
    import json

    from bench.common import RESULTS_DIR
    from bench.run import BENCHMARKS

    parser = argparse.ArgumentParser(prog="python -m bench.report")
    parser.add_argument("out", nargs="?", default="docs/benchmarks.md")
    parser.add_argument("--results", default=str(RESULTS_DIR))
    args = parser.parse_args(argv)
    from pathlib import Path

    results = []
    for name in BENCHMARKS:
        path = Path(args.results) / f"{name}.json"
        if path.exists():
            data = json.loads(path.read_text())
            results.append(data[0] if isinstance(data, list) else data)
    stamped = next((r for r in results if "machine" in r), None)
    if stamped is None:
        raise SystemExit(f"no benchmark JSON with a machine under {args.results}")
    Path(args.out).write_text(render(results, stamped["machine"], stamped["time"]))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
