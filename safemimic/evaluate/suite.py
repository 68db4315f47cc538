"""``safemimic evaluate --suite DIR``: every recording in DIR at every placement, in parallel.

Each (clip, placement) run is one :func:`~safemimic.evaluate.evaluation.evaluate` in a worker
process (``--jobs``), written to ``OUT/<clip>-<placement>/`` exactly as a single run writes its
folder; a file that cannot be evaluated is reported in its row and the others still run. Then:

- ``OUT/summary.json``: ``{"settings": {...}, "runs": [{"clip", "placement", "cbf", "nominal",
  "input"} | {"clip", "placement", "error"}], "goals": [...]}``, the run objects as in
  ``metrics.json``, the goals as :func:`~safemimic.evaluate.goals.goal_report` gives them;
- ``OUT/summary.md``: one row per run (:data:`COLUMNS`), then the goals: how many runs meet each
  of the project's safety and imitation goals, which fail, and which of those fail only because
  the evaluator's own floor already misses it (:mod:`safemimic.evaluate.goals`; also
  ``summary.json``'s ``"goals"``);
- ``OUT/summary.png``: the same at a glance (true contacts with and without the CBF, the robot-
  caused share, min true clearance, min self h, lag, RMS against the true person).

One progress bar covers every run (workers report their steps through a queue).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import queue
import sys
import threading
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

from safemimic.evaluate.fidelity import LAG_STAGES
from safemimic.evaluate.goals import goal_report, goals_markdown
from safemimic.evaluate.person import CameraModel, latency_text
from safemimic.evaluate.progress import ProgressBar
from services.perception.placement import check_placement

#: (header, what it shows) of summary.md's columns after clip and placement.
COLUMNS: tuple[tuple[str, str], ...] = (
    ("true contacts CBF / none (fixed bodies)", "steps with a robot surface inside the true person, with / without "
     "the CBF; in brackets, the CBF run's steps with the person inside a body no imitation joint moves (pelvis, "
     "legs): no controller avoids those"),
    ("robot-caused / commanded (CBF)", "of the CBF run's contact steps, those in which the robot closed a touching "
     "pair > 1 mm/s / of those, the ones in which the command u* itself closed it > 1 mm/s (the others: the servos "
     "trailing or settling behind their command)"),
    ("approaches / commanded (CBF)", "CBF run: steps at which the robot closed > 1 mm/s a pair whose true clearance "
     "is below φ / of those, the ones the command u* closed too; in brackets, how far it closed in over them (mm)"),
    ("stopped (s): stop / backing out / person lost", "CBF run: how long the robot aimed at rest instead of imitating "
     "because a person was inside a margin (the protective stop, safety.on_intrusion) / of that, backing an arm out of "
     "a person standing still inside it / how long it stood because a capsule of the person was lost (a body part "
     "perception stopped seeing, safety.lost_human_hold_s) or their state was stale"),
    ("min true clearance (mm)", "CBF run: smallest robot–person capsule surface distance at the simulated joints"),
    ("min self h (mm)", "CBF run: smallest self-pair barrier at the simulated joints (true_min_h_self)"),
    ("lag (ms) (target / command / servos) / limits floor", "CBF run: median delay of the simulated joints behind "
     "the true person's retargeted angles (fidelity columns: from 1 s after the person is first perceived, when the "
     "robot has left its home pose); in brackets the stages (lag_ms_target / _command / _servo): q_nom behind the "
     "truth (latency, point filter, the rate between frames), q_cbf behind q_nom (tracking, binding rows, "
     "acceleration bound), the simulated joints behind q_cbf; after the slash the lag of a robot that sees the true "
     "target one latency late, perfectly, and follows it as fast as safety.u_max and safety.accel_max allow "
     "(lag_ms_limits_floor: where it exceeds the goal, no controller within those bounds meets it)"),
    ("rms true free (rad): robot / latency floor", "CBF run: RMS of q_sim − q_true while no constraint binds / "
     "of q_true seen one camera latency late against q_true over the same steps (a robot exactly at what it was "
     "shown scores that: no controller that does not predict the person does better)"),
    ("arm direction p95 (°): robot / at target / seen late", "CBF run, free steps: 95th percentile of the angle "
     "between the person's and the robot's arm segments, at q_sim / with the robot exactly at q_true (the "
     "retargeting's own error) / at q_true one camera latency late (that error and the latency's: the floor)"),
)
_REPORT_EVERY = 50  # control steps between progress messages from a worker


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _placements(text: str) -> list[str]:
    """The placements of ``--placements``, comma-separated, an x,y,yaw placement's three numbers
    together (``facing,0.8,0.5,3.14``: facing and 0.8,0.5,3.14); ValueError for none or one that
    :func:`~services.perception.placement.parse_placement` refuses."""
    parts = [p.strip() for p in text.split(",") if p.strip()]
    placements = []
    while parts:
        take = 3 if _is_number(parts[0]) else 1
        placements.append(",".join(parts[:take]))
        parts = parts[take:]
    if not placements:
        raise ValueError("--placements needs at least one placement")
    for placement in placements:
        check_placement(placement, "--placements")
    return placements


def _run_one(index: int, clip: str, placement: str, args: dict[str, Any], camera: CameraModel, out: str,
             progress: Any) -> dict[str, Any]:
    """Worker: evaluate one clip at one placement and write its folder; the summary row."""
    from safemimic.evaluate.evaluation import evaluate, evaluation_config, write_outputs
    from safemimic.evaluate.main import INPUT_ERRORS, rrd_path

    row: dict[str, Any] = {"clip": Path(clip).stem, "placement": placement}

    def report(done: int, total: int) -> None:
        if done % _REPORT_EVERY == 0 or done == total:
            progress.put((index, done, total))

    try:
        conf = evaluation_config(clip, None, placement, args["robot_model"], args["config"])
        evaluation = evaluate(conf, args["seconds"], camera, report)
        folder = Path(out) / f"{row['clip']}-{placement}"
        metrics = write_outputs(evaluation, folder, rrd_path(args["rrd"], folder, suite=True))
    except INPUT_ERRORS as exc:
        return {**row, "error": str(exc)}
    return {**row, **{key: metrics[key] for key in ("cbf", "nominal", "input")}}


def _mm(value: float | None) -> str:
    return "—" if value is None else f"{1e3 * value:.1f}"


def _stopped(cbf: dict[str, Any], given: dict[str, Any]) -> str:
    """The stopped column: protective stop / backing-out / person-lost steps of a run, in seconds."""
    step_s = given["seconds"] / max(given["control_steps"], 1)
    return " / ".join(f"{cbf[key] * step_s:.2f}" for key in ("protective_stop_steps", "backing_out_steps",
                                                              "person_lost_steps"))


def _runs(settings: dict[str, Any]) -> str:
    """How the dropout's keypoints are hidden, after its probability: "" (independently per frame) or
    " in runs of L frames"."""
    frames = settings.get("dropout_frames", 0.0)
    return f" in runs of {frames:g} frames" if frames else ""


def _num(value: float | None, fmt: str) -> str:
    return "—" if value is None else format(value, fmt)


def summary_markdown(summary: dict[str, Any]) -> str:
    """summary.md: the settings, a row per run, the goals (:func:`goals_markdown` of the summary's
    ``"goals"``) and what each column means."""
    s = summary["settings"]
    lines = [
        "# Evaluation suite", "",
        f"{len(summary['runs'])} runs; camera latency {latency_text(s)}, depth noise {s['depth_noise_m']:g} m, "
        f"dropout {s['dropout']:g}{_runs(s)}, seed {s['seed']}; robot model {s['robot_model'] or 'default'}.", "",
        "| clip | placement | " + " | ".join(h for h, _ in COLUMNS) + " |",
        "|---|---|" + "---|" * len(COLUMNS),
    ]
    for run in summary["runs"]:
        if "error" in run:
            lines.append(f"| {run['clip']} | {run['placement']} | **failed:** {run['error']} |" + " |" * (len(COLUMNS) - 1))
            continue
        cbf, nominal = run["cbf"], run["nominal"]
        cells = [
            f"{cbf['true_contacts_robot_human']} / {nominal['true_contacts_robot_human']} "
            f"({cbf['true_contacts_fixed_bodies']})",
            f"{cbf['robot_caused_contact_steps']} / {cbf['robot_caused_contact_steps_commanded']}",
            f"{cbf['robot_approach_steps']} / {cbf['robot_approach_steps_commanded']} ({cbf['robot_approach_mm']:.1f})",
            _stopped(cbf, run["input"]),
            _mm(cbf["true_min_clearance_human"]),
            _mm(cbf["true_min_h_self"]),
            f"{_num(cbf['fidelity']['lag_ms'], '.0f')} "
            f"({' / '.join(_num(cbf['fidelity'][f'lag_ms_{stage}'], '.0f') for stage in LAG_STAGES)}) / "
            f"{_num(cbf['fidelity']['lag_ms_limits_floor'], '.0f')}",
            f"{_num(cbf['fidelity']['rms_true_free'], '.3f')} / "
            f"{_num(cbf['fidelity']['rms_true_free_latency_floor'], '.3f')}",
            " / ".join(_num(cbf["fidelity"][f"direction_error_deg_p95{floor}"], ".0f")
                       for floor in ("", "_at_target", "_latency_floor")),
        ]
        lines.append(f"| {run['clip']} | {run['placement']} | " + " | ".join(cells) + " |")
    lines += ["", *goals_markdown(summary["goals"])]
    lines += ["", "Columns:", ""] + [f"- **{h}**: {what}" for h, what in COLUMNS]
    return "\n".join(lines) + "\n"


def plot_summary(summary: dict[str, Any], path: Path) -> Path:
    """summary.png: one panel per quantity, a bar (pair) per run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker
    import numpy as np

    runs = [r for r in summary["runs"] if "error" not in r]
    labels = [f"{r['clip']}\n{r['placement']}" for r in runs]
    x = np.arange(len(runs))

    def values(run_key: str, key: str, scale: float = 1.0, sub: str | None = None) -> np.ndarray:
        out = []
        for r in runs:
            v = r[run_key][key] if sub is None else r[run_key][key][sub]
            out.append(np.nan if v is None else scale * v)
        return np.array(out, dtype=float)

    fig, axes = plt.subplots(2, 3, figsize=(max(10, 1.1 * len(runs) + 4), 7.5), constrained_layout=True)
    ax = axes[0, 0]
    ax.bar(x - 0.2, values("nominal", "true_contacts_robot_human"), 0.4, color="tab:red", label="without CBF")
    ax.bar(x + 0.2, values("cbf", "true_contacts_robot_human"), 0.4, color="tab:blue", label="with CBF")
    ax.bar(x + 0.2, values("cbf", "robot_caused_contact_steps"), 0.4, color="navy", label="with CBF, robot-caused")
    fixed = values("cbf", "true_contacts_fixed_bodies")
    ax.scatter(x + 0.2, np.where(fixed > 0, fixed, np.nan), marker="_", s=200, color="black", zorder=3,
               label="with CBF, the person inside a fixed body (floor)")
    ax.set_title("contact steps with the true person", fontsize=10)
    ax.set_ylabel("steps", fontsize=8)
    ax.legend(fontsize=7, framealpha=0.7)
    panels = [
        (axes[0, 1], values("cbf", "true_min_clearance_human", 1e3), "min true clearance, CBF (mm)", True),
        (axes[0, 2], values("cbf", "true_min_h_self", 1e3), "min self h at q_sim, CBF (mm)", True),
        (axes[1, 0], values("cbf", "fidelity", sub="lag_ms"), "lag behind the person, CBF (ms, log scale)", False),
        (axes[1, 1], values("cbf", "fidelity", sub="rms_true_free"), "RMS q_sim − q_true, free steps, CBF (rad)",
         False),
        (axes[1, 2], values("cbf", "fidelity", sub="direction_error_deg_p95"), "arm direction error p95, CBF (deg)",
         False),
    ]
    units = ("mm", "mm", "ms", "rad", "deg")
    for (ax, data, title, signed), unit in zip(panels, units, strict=True):
        ax.bar(x, data, 0.6, color=["tab:red" if signed and v < 0 else "tab:blue" for v in np.nan_to_num(data)])
        if signed:
            ax.axhline(0.0, color="black", lw=0.8)
        ax.set_title(title + ("; red: below 0" if signed else ""), fontsize=10)
        ax.set_ylabel(unit, fontsize=8)
    axes[1, 0].set_yscale("log")  # one walk-through's lag would flatten the goal and the floors
    axes[1, 0].yaxis.set_major_locator(matplotlib.ticker.FixedLocator([20, 50, 80, 200, 500, 1000, 2000]))
    axes[1, 0].yaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    axes[1, 0].yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    floor = axes[1, 1].scatter(x, values("cbf", "fidelity", sub="rms_true_free_latency_floor"), marker="_", s=200,
                               color="black", zorder=3, label="latency floor")
    rms_goal = axes[1, 1].axhline(0.05, color="tab:green", ls="--", lw=1.0, label="goal: 0.05 rad")
    axes[1, 1].legend(handles=[floor, rms_goal], fontsize=7, framealpha=0.7)
    retargeting = axes[1, 2].scatter(x, values("cbf", "fidelity", sub="direction_error_deg_p95_at_target"),
                                     marker="_", s=200, color="black", zorder=3, label="at the target (retargeting)")
    seen_late = axes[1, 2].scatter(x, values("cbf", "fidelity", sub="direction_error_deg_p95_latency_floor"),
                                   marker="_", s=200, color="tab:orange", zorder=3,
                                   label="at the target seen one latency late")
    direction_goal = axes[1, 2].axhline(15.0, color="tab:green", ls="--", lw=1.0, label="goal: 15°")
    axes[1, 2].legend(handles=[retargeting, seen_late, direction_goal], fontsize=7, framealpha=0.7)
    s = summary["settings"]
    target = axes[1, 0].scatter(x, values("cbf", "fidelity", sub="lag_ms_target"), marker="_", s=200, color="black",
                                zorder=3, label="of it, the target q_nom's (latency, point filter)")
    limits = axes[1, 0].scatter(x, values("cbf", "fidelity", sub="lag_ms_limits_floor"), marker="_", s=200,
                                color="tab:orange", zorder=3, label="the target seen late, within the speed and "
                                "acceleration bounds (floor)")
    goal = axes[1, 0].axhline(s["latency_ms"] + 20.0, color="tab:green", ls="--", lw=1.0, label="goal: latency + 20 ms")
    axes[1, 0].legend(handles=[target, limits, goal], fontsize=7, framealpha=0.7)
    for ax in (axes[0, 0], axes[1, 0], axes[1, 2]):  # room above the bars for the legend
        bottom, top = ax.get_ylim()
        ax.set_ylim(bottom, top * (4.0 if ax.get_yscale() == "log" else 1.5))
    for ax in axes.flat:
        ax.set_xticks(x, labels, rotation=60, ha="right", fontsize=7)
        ax.grid(alpha=0.3, axis="y")
    fig.suptitle(f"Evaluation suite: {len(runs)} runs, camera latency {latency_text(s)}", fontsize=11)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def run_suite(args: argparse.Namespace, camera: CameraModel) -> int:
    """The ``--suite`` command: 0 when every run was evaluated, 1 when some failed, 2 for bad arguments."""
    folder = Path(args.suite).expanduser()
    clips = sorted(folder.glob("*.npz")) if folder.is_dir() else []
    try:
        placements = _placements(args.placements)
        if args.jobs is not None and args.jobs < 1:
            raise ValueError(f"--jobs must be ≥ 1, got {args.jobs}")
        if not clips:
            raise ValueError(f"{folder}: no .npz recordings found" if folder.is_dir() else f"{folder} is not a folder")
    except ValueError as exc:
        print(f"safemimic evaluate: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tasks = [(str(clip), placement) for clip in clips for placement in placements]
    options = {"robot_model": args.robot_model, "config": args.config, "seconds": args.seconds,
               "rrd": getattr(args, "rrd", None)}
    jobs = min(args.jobs or os.cpu_count() or 1, len(tasks))
    bar = None if args.quiet else ProgressBar(1000, f"evaluate {len(tasks)} runs ({jobs} jobs)")
    fractions = [0.0] * len(tasks)
    context = multiprocessing.get_context("spawn")  # clean workers: no forked MuJoCo/numba state
    with context.Manager() as manager:
        progress = manager.Queue()
        done_event = threading.Event()

        def drain() -> None:
            while not done_event.is_set():
                try:
                    index, done, total = progress.get(timeout=0.2)
                except (queue.Empty, EOFError, OSError):
                    continue
                fractions[index] = done / max(total, 1)
                if bar is not None:
                    bar.update(round(1000 * sum(fractions) / len(tasks)))

        reader = threading.Thread(target=drain, daemon=True)
        reader.start()
        rows: list[dict[str, Any] | None] = [None] * len(tasks)
        with ProcessPoolExecutor(max_workers=jobs, mp_context=context) as pool:
            futures = {pool.submit(_run_one, i, clip, placement, options, camera, str(out), progress): i
                       for i, (clip, placement) in enumerate(tasks)}
            for future in as_completed(futures):
                i = futures[future]
                try:
                    rows[i] = future.result()
                except Exception as exc:  # a worker that died: the row says so, the rest go on
                    clip, placement = tasks[i]
                    rows[i] = {"clip": Path(clip).stem, "placement": placement, "error": f"{type(exc).__name__}: {exc}"}
                fractions[i] = 1.0
        done_event.set()
        reader.join(timeout=1.0)
    if bar is not None:
        bar.close()
    summary = {
        "settings": {**camera.settings(), "seconds": args.seconds, "robot_model": args.robot_model,
                     "config": args.config, "placements": placements, "clips": [c.name for c in clips], "jobs": jobs},
        "runs": rows,
        "goals": goal_report(rows),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n")
    markdown = summary_markdown(summary)
    (out / "summary.md").write_text(markdown)
    plot_summary(summary, out / "summary.png")
    failed = [r for r in rows if r is not None and "error" in r]
    print(markdown)
    for row in failed:
        print(f"safemimic evaluate: {row['clip']} ({row['placement']}) failed: {row['error']}", file=sys.stderr)
    print(f"wrote {out}/summary.json, summary.md, summary.png and {len(rows) - len(failed)} run folders")
    return 1 if failed else 0
