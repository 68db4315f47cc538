"""Canonical skeleton and the ``.npz`` recording format (architecture §3, §6).

A recording holds ``names`` (K canonical keypoint names, any order), ``t`` (T,) seconds,
``xyz`` (T, K, 3) metres, z up, ``fps`` (scalar), optional ``conf`` (T, K) in [0, 1] and
``source`` (text). Reading maps the file's keypoints into the canonical order of
:data:`shared.names.KEYPOINT_NAMES`; keypoints absent from the file are NaN with confidence 0
(missing, never invented: :func:`with_hip_centre_pelvis` is the one completion, which the replay
source asks for). Extra keys in the file are ignored, except those that look like another way of
marking missing keypoints (:data:`_VALIDITY_KEYS`: ``valid``, ``mask``, ...), which are refused:
evaluated as if absent, zeros meant as missing would be read as points at the origin. Refused as
well: a file whose person does not stand along z (a y-up file, axes swapped:
:func:`_check_upright`), whose limbs are not a person's in metres (:func:`_check_units`), with no
keypoint in any frame, or whose ``t`` does not step by about 1/``fps`` seconds (``t`` in
milliseconds or nanoseconds, a wrong ``fps``).
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from shared.errors import SafemimicError
from shared.messages import MAX_COORD_M
from shared.names import KEYPOINT_INDEX, KEYPOINT_NAMES

#: Segments used to check units: a human upper arm/forearm/thigh is 0.15–0.6 m long.
_UNIT_CHECK_SEGMENTS = (("left_shoulder", "left_elbow"), ("right_shoulder", "right_elbow"), ("left_hip", "left_knee"))
_MAX_SEGMENT_M = 1.0
#: ... and at least this long (a small child's upper arm is ≈ 0.15 m): catches a file in km or
#: scaled by mistake, whose "person" the robot would never meet.
_MIN_SEGMENT_M = 0.08
#: The median step of ``t`` may differ from 1/``fps`` by at most this factor (frames dropped now and
#: then, a rounded fps), not by the 1,000 of milliseconds.
_MAX_PERIOD_RATIO = 2.0
#: Keys that would mark missing keypoints in another format than ``conf`` and NaN.
_VALIDITY_KEYS = ("valid", "mask", "visible", "visibility", "present", "missing")
#: A recording is z up when its torso (pelvis or hip centre → shoulder centre) is within 60° of +z
#: (cos ≥ 0.5) in the median frame: a person bending, turning or lying back now and then stays far
#: above, a y-up file's torso lies along a horizontal axis (cos ≈ 0) and an upside-down one at −1.
_MIN_UPRIGHT_COS = 0.5


class RecordingError(SafemimicError, ValueError):
    """A recording file is unreadable or violates the format; the message says what and where."""


@dataclass(frozen=True)
class Recording:
    """A skeleton recording in canonical keypoint order: ``xyz`` (T, 15, 3) m, ``conf`` (T, 15)."""

    t: np.ndarray
    xyz: np.ndarray
    conf: np.ndarray
    fps: float
    source: str = ""

    @property
    def valid(self) -> np.ndarray:
        """(T, 15) bool: keypoint present (finite, confidence > 0)."""
        return np.isfinite(self.xyz).all(axis=-1) & (self.conf > 0)

    def __len__(self) -> int:
        return len(self.t)


def _require(condition: bool, path: Path, message: str) -> None:
    if not condition:
        raise RecordingError(f"{path}: {message}")


def read_npz(path: str | Path) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` file ``path`` by its key, unchecked; :class:`RecordingError` when
    the file is missing, empty or not an ``.npz`` (no pickled objects)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            return {key: data[key] for key in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise RecordingError(f"{path}: cannot read as .npz: {exc}") from None


def read_recording(path: str | Path) -> Recording:
    """Read and check a ``.npz`` recording; :class:`RecordingError` on any violation."""
    path = Path(path)
    arrays = read_npz(path)
    for key in ("names", "t", "xyz", "fps"):
        _require(key in arrays, path, f"missing required key {key!r} (has: {', '.join(sorted(arrays))})")

    names = [str(n) for n in np.atleast_1d(arrays["names"])]
    unknown = [n for n in names if n not in KEYPOINT_INDEX]
    _require(not unknown, path, f"unknown keypoint names {unknown}; canonical: {', '.join(KEYPOINT_NAMES)}")
    _require(len(set(names)) == len(names), path, "duplicate keypoint names")

    t = np.asarray(arrays["t"], dtype=np.float64)
    xyz = np.asarray(arrays["xyz"], dtype=np.float64)
    _require(t.ndim == 1 and len(t) > 0, path, f"'t' must have shape (T,) with T > 0, got {t.shape}")
    n_frames = len(t)
    _require(xyz.shape == (n_frames, len(names), 3), path, f"'xyz' must have shape ({n_frames}, {len(names)}, 3), got {xyz.shape}")
    _require(bool(np.isfinite(t).all()) and bool((np.diff(t) > 0).all()), path, "'t' must be finite and strictly increasing")
    fps = float(np.asarray(arrays["fps"]).reshape(()))
    _require(np.isfinite(fps) and 0 < fps <= 10000, path, f"'fps' must be in (0, 10000], got {fps}")
    if n_frames > 1:
        step = float(np.median(np.diff(t)))
        _require(1.0 / _MAX_PERIOD_RATIO <= step * fps <= _MAX_PERIOD_RATIO, path,
                 f"'t' steps by {step:g} (median) but 'fps' {fps:g} means {1.0 / fps:g} s: 't' must be in seconds, "
                 "'fps' the frames per second")
    marks = [key for key in _VALIDITY_KEYS if key in arrays]
    _require(not marks, path, f"key {marks[0]!r} is not part of the format: mark a missing keypoint with NaN in 'xyz' "
             "or 0 in 'conf' (T, K)" if marks else "")

    conf_in = np.ones((n_frames, len(names))) if "conf" not in arrays else np.asarray(arrays["conf"], dtype=np.float64)
    _require(conf_in.shape == (n_frames, len(names)), path, f"'conf' must have shape ({n_frames}, {len(names)}), got {conf_in.shape}")
    _require(bool(((conf_in >= 0) & (conf_in <= 1)).all()), path, "'conf' must lie in [0, 1]")

    finite = np.isfinite(xyz)
    canonical_xyz = np.full((n_frames, len(KEYPOINT_NAMES), 3), np.nan)
    canonical_conf = np.zeros((n_frames, len(KEYPOINT_NAMES)))
    index = [KEYPOINT_INDEX[n] for n in names]
    canonical_xyz[:, index] = xyz
    canonical_conf[:, index] = np.where(finite.all(axis=-1), conf_in, 0.0)
    _require(bool((canonical_conf > 0).any()), path, "no keypoint in any frame (every point NaN or of confidence 0)")
    _check_units(canonical_xyz, path)
    _check_upright(canonical_xyz, path)
    _require(bool((np.abs(xyz[finite]) < MAX_COORD_M).all()), path, f"coordinates beyond {MAX_COORD_M} m from the origin")

    source = str(arrays["source"]) if "source" in arrays else ""
    return Recording(t=t, xyz=canonical_xyz, conf=canonical_conf, fps=fps, source=source)


def _check_units(xyz: np.ndarray, path: Path) -> None:
    """Limb lengths must be human in metres, within [:data:`_MIN_SEGMENT_M`, :data:`_MAX_SEGMENT_M`]
    (median over the frames: catches centimetre or millimetre files, and a person scaled to a toy)."""
    for a, b in _UNIT_CHECK_SEGMENTS:
        lengths = np.linalg.norm(xyz[:, KEYPOINT_INDEX[a]] - xyz[:, KEYPOINT_INDEX[b]], axis=-1)
        lengths = lengths[np.isfinite(lengths)]
        if lengths.size:
            median = float(np.median(lengths))
            _require(_MIN_SEGMENT_M <= median <= _MAX_SEGMENT_M, path,
                     f"{a}–{b} is {median:.3g} long: units must be metres (a person's is 0.15–0.6 m)")


def hip_centre(xyz: np.ndarray) -> np.ndarray:
    """(…, 3) the midpoint of the hips of canonical points ``xyz`` (…, 15, 3) (NaN where a hip is)."""
    return 0.5 * (xyz[..., KEYPOINT_INDEX["left_hip"], :] + xyz[..., KEYPOINT_INDEX["right_hip"], :])


def _check_upright(xyz: np.ndarray, path: Path) -> None:
    """The person must stand along +z (the format is z up): in the median frame with a torso, the
    unit vector from the pelvis (the hip centre where it is missing) to the shoulder centre has a z
    component ≥ :data:`_MIN_UPRIGHT_COS`. Frames without a torso say nothing; none: no check."""
    pelvis = xyz[:, KEYPOINT_INDEX["pelvis"]]
    pelvis = np.where(np.isfinite(pelvis).all(axis=-1, keepdims=True), pelvis, hip_centre(xyz))
    shoulders = 0.5 * (xyz[:, KEYPOINT_INDEX["left_shoulder"]] + xyz[:, KEYPOINT_INDEX["right_shoulder"]])
    torso = shoulders - pelvis
    length = np.linalg.norm(torso, axis=-1)
    seen = np.isfinite(length) & (length > 0.05)
    if seen.any():
        up = float(np.median(torso[seen, 2] / length[seen]))
        _require(up >= _MIN_UPRIGHT_COS, path,
                 f"the person does not stand along z (torso to +z: median cos {up:.2f}, needs ≥ {_MIN_UPRIGHT_COS}): "
                 "the format is z up, metres; a y-up file needs its axes swapped")


def with_hip_centre_pelvis(recording: Recording) -> Recording:
    """``recording`` with the pelvis, where it is missing and both hips are present, at the hip
    centre, its confidence the smaller of the hips': the pelvis as the camera sources define it
    (:mod:`services.perception.camera`), so a file from a skeleton without one (COCO-style
    estimators) or with it occluded keeps its torso angles and capsule. Other keypoints as they are."""
    pelvis = KEYPOINT_INDEX["pelvis"]
    hips = [KEYPOINT_INDEX["left_hip"], KEYPOINT_INDEX["right_hip"]]
    valid = recording.valid
    fill = ~valid[:, pelvis] & valid[:, hips].all(axis=1)
    if not fill.any():
        return recording
    xyz, conf = recording.xyz.copy(), recording.conf.copy()
    xyz[fill, pelvis] = hip_centre(xyz[fill])
    conf[fill, pelvis] = conf[fill][:, hips].min(axis=1)
    return replace(recording, xyz=xyz, conf=conf)


def write_recording(path: str | Path, recording: Recording, names: tuple[str, ...] = KEYPOINT_NAMES) -> Path:
    """Write ``recording`` as ``.npz`` (canonical names; NaN where a keypoint is missing)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    index = [KEYPOINT_INDEX[n] for n in names]
    np.savez_compressed(
        path,
        names=np.array(names),
        t=recording.t,
        xyz=recording.xyz[:, index],
        fps=np.float64(recording.fps),
        conf=recording.conf[:, index],
        source=np.array(recording.source),
    )
    return path
