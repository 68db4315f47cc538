"""Point filter: lag on real motion against jitter on still photographs, EMA against One Euro.

* **lag** (ms): for each motion clip (architecture §6 ``.npz``) in the folder ``$SAFEMIMIC_MOCAP_DIR``
  names (``make bench`` passes the team's development clips; none: no lag figures), the delay d
  that best aligns the filtered keypoints with the raw ones:
  d* = argmin_d mean_{t,k} ‖x̂_k(t) − x_k(t − d)‖² over d ∈ [0, 200] ms in 1 ms steps (x linearly
  interpolated between frames; the first 0.5 s skipped). Reported per clip and the mean over clips.
* **jitter** (mm): the camera source (BlazePose → PnP → robot frame) on scikit-image's
  ``astronaut.png`` and ``camera.png``, each written as a 30 fps video of ``STILL_FRAMES`` identical
  frames: every keypoint the source sees in every frame is a still point, so all its motion is
  noise. Jitter = RMS over those points of the filtered position's standard deviation over time
  (after ``WARMUP`` frames), mean over the two photographs; also the RMS frame-to-frame step.

Every filter setting runs the same :class:`~services.perception.point_filter.PointFilter` (jump
rejection, hold, reset as shipped), only ``kind`` and its parameters change. The One Euro grid is
searched for the lowest mean lag whose jitter does not exceed the EMA's. Writes
``bench/results/point_filter.json`` and prints a table.
"""

from __future__ import annotations

import os
import tempfile
import threading
from pathlib import Path
from typing import Any

import numpy as np

from services.perception.point_filter import PointFilter
from shared.config import PerceptionConfig, PointFilterConfig
from shared.skeleton import read_recording

FPS = 30.0
STILL_FRAMES = 90
WARMUP = 10
SKIP_S = 0.5
DELAYS_MS = np.arange(0.0, 201.0, 1.0)
PHOTOGRAPHS = ("astronaut", "camera")
MIN_CUTOFFS_HZ = (0.5, 1.0, 2.0, 3.0, 5.0)
BETAS = (0.0, 1.0, 2.0, 5.0, 10.0, 20.0, 30.0, 40.0)
D_CUTOFF_HZ = 1.0


#: The environment variable naming the folder of motion clips the lag is measured on.
MOCAP_ENV = "SAFEMIMIC_MOCAP_DIR"


def clip_paths() -> list[Path]:
    """The ``.npz`` clips in ``$SAFEMIMIC_MOCAP_DIR`` (sorted; none if it is unset or missing)."""
    folder = os.environ.get(MOCAP_ENV)
    return sorted(Path(folder).glob("*.npz")) if folder and Path(folder).is_dir() else []


def filtered(conf: PointFilterConfig, t: np.ndarray, xyz: np.ndarray, confidence: np.ndarray) -> np.ndarray:
    """(T, K, 3) filter output (NaN where invalid) for frames at times ``t``."""
    filt = PointFilter(conf, xyz.shape[1])
    out = np.full(xyz.shape, np.nan)
    for i in range(len(t)):
        frame = filt(float(t[i]), xyz[i], confidence[i])
        out[i][frame.valid] = frame.points[frame.valid]
    return out


def best_delay_ms(t: np.ndarray, raw: np.ndarray, smooth: np.ndarray) -> float:
    """d* = argmin_d mean ‖x̂(t) − x(t − d)‖² (module docstring), in ms."""
    use = t >= t[0] + SKIP_S
    flat, target = raw.reshape(len(t), -1), smooth.reshape(len(t), -1)[use]
    errors = []
    for delay in DELAYS_MS / 1e3:
        at = np.clip(t[use] - delay, t[0], t[-1])  # linear interpolation of every column at t − d
        right = np.clip(np.searchsorted(t, at, side="right"), 1, len(t) - 1)
        weight = ((at - t[right - 1]) / (t[right] - t[right - 1]))[:, None]
        diff = target - (flat[right - 1] * (1.0 - weight) + flat[right] * weight)
        errors.append(float(np.nanmean(diff * diff)))
    return float(DELAYS_MS[int(np.argmin(errors))])


def still_frames() -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(t, xyz, conf) of the camera source on each photograph repeated as a video; {} if unavailable."""
    try:
        import cv2
        import skimage.data

        from services.perception.camera.model import ModelError, locate_models, model_dir
        from services.perception.sources import open_source
    except ImportError:
        return {}
    conf = PerceptionConfig(source="camera", realtime=False)
    try:
        locate_models(model_dir(conf.camera.model_dir))
    except ModelError:
        return {}
    out = {}
    with tempfile.TemporaryDirectory(prefix="safemimic-bench-") as folder:
        for name in PHOTOGRAPHS:
            image = getattr(skimage.data, name)()
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR if image.ndim == 2 else cv2.COLOR_RGB2BGR)
            video = Path(folder) / f"{name}.avi"
            writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), FPS, image.shape[1::-1])
            for _ in range(STILL_FRAMES):
                writer.write(image)
            writer.release()
            source = open_source(conf.model_copy(update={"camera": conf.camera.model_copy(update={"device": str(video)})}))
            frames = list(source.frames(threading.Event()))
            out[name] = (np.array([f.t for f in frames]), np.array([f.xyz for f in frames]), np.array([f.conf for f in frames]))
    return out


def jitter_mm(smooth: np.ndarray) -> tuple[float, float]:
    """(RMS positional std, RMS frame-to-frame step) in mm over points valid in every frame after WARMUP."""
    tail = smooth[WARMUP:]
    seen = np.isfinite(tail).all(axis=(0, 2))
    tail = tail[:, seen]
    spread = np.sqrt((tail.std(axis=0) ** 2).sum(axis=1))  # per point, 3-D
    steps = np.linalg.norm(np.diff(tail, axis=0), axis=2)
    return float(np.sqrt((spread**2).mean()) * 1e3), float(np.sqrt((steps**2).mean()) * 1e3)


def measure(conf: PointFilterConfig, clips: dict[str, Any], stills: dict[str, Any]) -> dict[str, Any]:
    lags = {name: best_delay_ms(t, xyz, filtered(conf, t, xyz, np.ones(xyz.shape[:2]))) for name, (t, xyz) in clips.items()}
    jitter = {name: jitter_mm(filtered(conf, t, xyz, c)) for name, (t, xyz, c) in stills.items()}
    return {
        "kind": conf.kind.value,
        "params": {"ema_tau_s": conf.ema_tau_s} if conf.kind.value == "ema" else
                  {"min_cutoff_hz": conf.min_cutoff_hz, "beta": conf.beta, "d_cutoff_hz": conf.d_cutoff_hz},
        "lag_ms": lags,
        "lag_ms_mean": float(np.mean(list(lags.values()))) if lags else None,
        "jitter_mm": {name: j[0] for name, j in jitter.items()},
        "step_mm": {name: j[1] for name, j in jitter.items()},
        "jitter_mm_mean": float(np.mean([j[0] for j in jitter.values()])) if jitter else None,
        "step_mm_mean": float(np.mean([j[1] for j in jitter.values()])) if jitter else None,
    }


def run() -> dict[str, Any]:
    clips = {}
    for path in clip_paths():
        recording = read_recording(path)
        clips[path.stem] = (np.asarray(recording.t, float), np.asarray(recording.xyz, float))
    stills = still_frames()
    shipped = PointFilterConfig()

    def variant(**fields: Any) -> PointFilterConfig:
        return PointFilterConfig.model_validate({**shipped.model_dump(), **fields})

    ema = measure(variant(kind="ema"), clips, stills)
    raw = measure(variant(kind="ema", ema_tau_s=0.0), clips, stills)
    grid = [
        measure(variant(kind="one_euro", min_cutoff_hz=f, beta=b, d_cutoff_hz=D_CUTOFF_HZ), clips, stills)
        for f in MIN_CUTOFFS_HZ for b in BETAS
    ]
    admissible = [r for r in grid if r["jitter_mm_mean"] is None or ema["jitter_mm_mean"] is None
                  or r["jitter_mm_mean"] <= ema["jitter_mm_mean"]]
    best = min(admissible or grid, key=lambda r: r["lag_ms_mean"] if r["lag_ms_mean"] is not None else 0.0)
    current = measure(shipped, clips, stills)
    result = {
        "name": "point_filter",
        "unit": "ms",
        "p50": current["lag_ms_mean"] or 0.0,  # the shipped default's mean lag over the clips
        "p99": max(current["lag_ms"].values(), default=0.0),  # its worst clip
        "what": "lag: delay best aligning filtered with raw mocap keypoints; jitter: camera source on still photographs",
        "clips": sorted(clips),
        "photographs": sorted(stills) or "skipped: camera extra or pose model missing",
        "default": current,
        "raw": raw,
        "ema": ema,
        "one_euro_best_at_ema_jitter": best,
        "one_euro_grid": grid,
    }
    print_table(result)
    return result


def print_table(result: dict[str, Any]) -> None:
    rows = [("raw (no smoothing)", result["raw"]), ("ema", result["ema"]),
            ("one_euro (best at ≤ ema jitter)", result["one_euro_best_at_ema_jitter"]), ("shipped default", result["default"])]
    print(f"\n{'filter':<34}{'params':<44}{'lag ms':>8}{'jitter mm':>11}{'step mm':>9}")
    for label, r in rows:
        params = ", ".join(f"{k}={v:g}" for k, v in r["params"].items())
        fmt = lambda v: "-" if v is None else f"{v:.1f}"  # noqa: E731
        print(f"{label:<34}{params:<44}{fmt(r['lag_ms_mean']):>8}{fmt(r['jitter_mm_mean']):>11}{fmt(r['step_mm_mean']):>9}")


if __name__ == "__main__":
    from bench.common import write_result

    print(write_result(run()))
