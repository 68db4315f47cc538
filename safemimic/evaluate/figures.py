"""The paper's Fig. 2b/3b for one evaluation: joint trajectories, and every monitored barrier h.

``joints.png``: the 8 imitation joints over time, the waist, the left arm and the right arm a row
each — the true person's retargeted angles q_true, the perceived target q_nom, the simulated joints
without the CBF layer and with it, and the lag's limits floor; where a CBF row binds the background
is shaded yellow, where the robot is in a protective stop (it aims at rest, not at the person) pink.
``barriers.png``: every monitored h over time in the CBF run (thin lines), self pairs above and
robot–human pairs below, with the minimum over the pairs of both runs as the filter sees them (the
commanded joints, the perceived person), the zero line, the line where the capsules touch
(h = −φ), the standoff from the person (h = D, ``safety.human_standoff_m``, when set) and the
global minimum of each run marked; in green the CBF run's true minimum (q_sim against the true
person, as h = clearance − φ), its minimum marked with the value ``summary.md`` reports; below, the
steps at which the person was inside a body no imitation joint moves (grey) and at which the robot
closed on them (red ticks: robot-caused).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from safemimic.evaluate.episode import Episode  # noqa: E402
from safemimic.evaluate.person import TruePerson  # noqa: E402

SAFE_COLOR = "tab:blue"
UNSAFE_COLOR = "tab:red"
NOMINAL_COLOR = "0.55"
TRUE_COLOR = "tab:green"
FLOOR_COLOR = "tab:purple"
BINDING_COLOR = "#fff3b0"
STOP_COLOR = "#f9d0d0"
FIXED_COLOR = "0.85"
_DPI = 110
#: Barrier plots show h up to this (m): far pairs would squash the interesting part.
_H_TOP = 0.35


def _shade(ax, ep: Episode, steps: np.ndarray, color: str) -> None:
    """Shade the time spans of ``ep`` where ``steps`` (N,) holds."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], steps.astype(np.int8), [0]])))
    dt = ep.t[1] - ep.t[0] if len(ep.t) > 1 else 0.0
    for start, stop in zip(edges[::2], edges[1::2]):
        ax.axvspan(ep.t[start], ep.t[stop - 1] + dt, color=color, lw=0, zorder=0)


def _shade_binding(ax, ep: Episode) -> None:
    """Shade the time spans where some CBF row binds in ``ep``, and (over them) its protective stops."""
    _shade(ax, ep, ep.binding, BINDING_COLOR)
    _shade(ax, ep, ep.stopped, STOP_COLOR)


def plot_joints(cbf: Episode, nominal: Episode, person: TruePerson, limits_floor: np.ndarray,
                joint_names: tuple[str, ...], path: Path, title: str) -> Path:
    """Write ``joints.png``: q_true, q_nom, q without and with the CBF layer for each joint (rad), and
    ``limits_floor`` (N, 8) rad, the robot following q_true seen one latency late within its bounds
    (:func:`~safemimic.evaluate.metrics.limits_floor_joints`: the best it could do)."""
    fig, axes = plt.subplots(3, 3, figsize=(13, 8.5), sharex=True, constrained_layout=True)
    # the waist's two joints in the first row (its third cell holds the legend), each arm in a row
    cells = [axes[0, 0], axes[0, 1], *axes[1], *axes[2]]
    for j, (ax, name) in enumerate(zip(cells, joint_names)):
        _shade_binding(ax, cbf)
        ax.plot(person.t, person.q_true[:, j], color=TRUE_COLOR, lw=1.0, label="q_true (the person, retargeted)")
        ax.plot(cbf.t, cbf.q_nom[:, j], color=NOMINAL_COLOR, lw=1.0, label="q_nom (the target, perceived)")
        ax.plot(person.t, limits_floor[:, j], color=FLOOR_COLOR, lw=0.9, ls=":",
                label="floor: q_true seen one latency late, followed within the speed and acceleration bounds")
        ax.plot(nominal.t, nominal.q_sim[:, j], color=UNSAFE_COLOR, lw=1.3, ls="--", label="robot without CBF (simulated)",
                zorder=3)
        ax.plot(cbf.t, cbf.q_sim[:, j], color=SAFE_COLOR, lw=1.5, label="robot with CBF (simulated)")
        ax.set_title(name.removesuffix("_joint").replace("_", " "), fontsize=9)
        ax.set_ylabel("rad", fontsize=8)
        ax.tick_params(labelsize=8, labelbottom=True)
        ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    handles, labels = cells[0].get_legend_handles_labels()
    handles += [plt.Rectangle((0, 0), 1, 1, color=BINDING_COLOR), plt.Rectangle((0, 0), 1, 1, color=STOP_COLOR)]
    labels += ["a CBF constraint binds", "protective stop (aims at rest)"]
    axes[0, 2].axis("off")
    axes[0, 2].legend(handles, labels, loc="center", fontsize=8, frameon=False)
    fig.suptitle(f"Joint trajectories without and with the CBF — {title}", fontsize=11)
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def _envelope(ep: Episode, columns: np.ndarray) -> np.ndarray:
    """Per step, the minimum h over ``columns`` (NaN where all are missing)."""
    values = np.where(np.isnan(ep.h[:, columns]), np.inf, ep.h[:, columns])
    low = values.min(axis=1, initial=np.inf)
    return np.where(np.isfinite(low), low, np.nan)


def _mark_true_minimum(ax, ep: Episode, true_low: np.ndarray, phi: float, self_pairs: bool) -> None:
    """Mark the smallest true h (m) of ``ep`` with what ``summary.md`` reports for it: the self pairs'
    h (``true_min_h_self``) or the person's clearance h + φ (``true_min_clearance_human``)."""
    if not np.isfinite(true_low).any():
        return
    k = int(np.nanargmin(np.where(np.isfinite(true_low), true_low, np.nan)))
    text = (f"true: min h = {1e3 * true_low[k]:.1f} mm" if self_pairs else
            f"true: min clearance = {1e3 * (true_low[k] + phi):.1f} mm")
    ax.plot(ep.t[k], true_low[k], "D", color=TRUE_COLOR, ms=6, mec="black", zorder=6)
    early = ep.t[k] - ep.t[0] < 0.3 * (ep.t[-1] - ep.t[0])  # then the text goes right of the mark, else left
    ax.annotate(f"{text}\nat {ep.t[k]:.2f} s", (ep.t[k], true_low[k]), xytext=(20 if early else -150, -30),
                textcoords="offset points",
                fontsize=8, color="darkgreen", arrowprops={"arrowstyle": "-", "color": TRUE_COLOR, "lw": 0.8})


def _mark_minimum(ax, ep: Episode, low: np.ndarray, columns: np.ndarray, color: str, run: str) -> None:
    if np.isnan(low).all():
        return
    k = int(np.nanargmin(low))
    row = np.flatnonzero(columns)[int(np.nanargmin(np.where(np.isnan(ep.h[k, columns]), np.inf, ep.h[k, columns])))]
    ax.plot(ep.t[k], low[k], "o", color=color, ms=7, mec="black", zorder=5)
    ax.annotate(
        f"{run}: min h = {1e3 * low[k]:.1f} mm\nat {ep.t[k]:.2f} s ({ep.pairs.names[row]})",
        (ep.t[k], low[k]), xytext=(8, -28 if run == "without CBF" else 12), textcoords="offset points",
        fontsize=8, color=color, arrowprops={"arrowstyle": "-", "color": color, "lw": 0.8},
    )


def plot_barriers(cbf: Episode, nominal: Episode, phi: float, path: Path, title: str, standoff: float = 0.0) -> Path:
    """Write ``barriers.png``: every monitored h (m) over time, self and robot–human pairs (``phi`` φ and
    ``standoff`` D in m; D = 0: no standoff line)."""
    fig, axes = plt.subplots(2, 1, figsize=(11, 7.5), sharex=True, constrained_layout=True)
    is_self = cbf.pairs.is_self
    for ax, columns, kind in ((axes[0], is_self, "self pairs"), (axes[1], ~is_self, "robot–human pairs")):
        _shade_binding(ax, cbf)
        if kind != "self pairs":
            _shade(ax, cbf, cbf.fixed_contact, FIXED_COLOR)
        n_rows = int(np.count_nonzero(columns))
        for row in np.flatnonzero(columns):
            ax.plot(cbf.t, cbf.h[:, row], lw=0.6, alpha=0.45)
        unsafe, safe = _envelope(nominal, columns), _envelope(cbf, columns)
        ax.plot(nominal.t, unsafe, color=UNSAFE_COLOR, lw=1.6, ls="--", label="min h without CBF (as perceived)")
        ax.plot(cbf.t, safe, color=SAFE_COLOR, lw=3.0, alpha=0.6,
                label="min h with CBF, the filter's view (commanded joints, perceived person)")
        true_columns = cbf.truth_is_self if kind == "self pairs" else ~cbf.truth_is_self
        true_low = np.where(np.isnan(cbf.true_clearance[:, true_columns]), np.inf, cbf.true_clearance[:, true_columns])
        true_low = true_low.min(axis=1, initial=np.inf) - phi
        ax.plot(cbf.t, np.where(np.isfinite(true_low), true_low, np.nan), color=TRUE_COLOR, lw=1.2, zorder=4,
                label="true min h with CBF (simulated joints, true person; summary.md's)")
        _mark_true_minimum(ax, cbf, true_low, phi, kind == "self pairs")
        ax.axhline(0.0, color="black", lw=1.0, label="h = 0 (safety boundary)")
        ax.axhline(-phi, color="black", lw=0.8, ls=":", label=f"h = −φ (capsules touch, φ = {1e3 * phi:g} mm)")
        if standoff > 0.0 and kind != "self pairs":
            ax.axhline(standoff, color="grey", lw=0.8, ls="-.",
                       label=f"h = D (standoff {1e3 * standoff:g} mm: the robot closes no nearer)")
        _mark_minimum(ax, nominal, unsafe, columns, UNSAFE_COLOR, "without CBF")
        _mark_minimum(ax, cbf, safe, columns, SAFE_COLOR, "with CBF")
        finite = np.concatenate([unsafe[np.isfinite(unsafe)], safe[np.isfinite(safe)], true_low[np.isfinite(true_low)],
                                 [0.0]])
        bottom = min(finite.min(), -phi) - 0.02
        ax.set_ylim(bottom, min(max(finite.max(), 0.05), _H_TOP) + 0.02)
        if kind != "self pairs":
            caused = np.flatnonzero(cbf.robot_caused)
            ax.plot(cbf.t[caused], np.full(len(caused), bottom), "|", color=UNSAFE_COLOR, ms=10, mew=1.2,
                    label=f"robot-caused contact step ({len(caused)})")
            ax.add_patch(plt.Rectangle((0, 0), 0, 0, color=FIXED_COLOR,
                                       label="the person inside a body no imitation joint moves (pelvis, legs)"))
        ax.set_title(f"{kind}: {n_rows} barriers h (thin: each pair with CBF)", fontsize=10)
        ax.set_ylabel("h (m)")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    axes[-1].set_xlabel("time (s)")
    fig.suptitle(f"Safety margins and their global minimum — {title}", fontsize=11)
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path
