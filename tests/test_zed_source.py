"""The ``zed`` source: the BODY_18 / BODY_34 → canonical mapping (no SDK needed) and, where the ZED
SDK's ``pyzed`` is installed, the source itself (skipped with the import error where it is not)."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from services.perception.camera.geometry import body_to_robot
from services.perception.camera.zed import BODY_18, BODY_34, BODY_FORMATS, zed_skeleton
from services.perception.sources import SourceUnavailable, open_source
from services.perception.synthetic import skeleton
from shared.config import CameraExtrinsics, PerceptionConfig
from shared.names import KEYPOINT_INDEX as K
from shared.names import KEYPOINT_NAMES

MIN_CONFIDENCE = PerceptionConfig().point_filter.min_confidence
IDENTITY = body_to_robot(CameraExtrinsics(position=[0.0, 0.0, 0.0], rpy=[0.0, 0.0, 0.0]))


def zed_body(body_format: str, canonical: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A ZED body array holding ``canonical`` (15, 3) at the mapped indices (a point made of two
    otherwise unused keypoints, e.g. BODY_18's head from the ears, split about it), other keypoints
    random; confidences 90 (the SDK's 0–100 scale)."""
    count, mapping = BODY_FORMATS[body_format]
    keypoints = rng.normal(size=(count, 3))
    singles = {sources[0] for sources in mapping.values() if len(sources) == 1}
    for name, sources in mapping.items():
        if len(sources) == 1:
            keypoints[sources[0]] = canonical[K[name]]
        elif not singles & set(sources):
            keypoints[list(sources)] = canonical[K[name]] + np.array([[0.0, 0.08, 0.0], [0.0, -0.08, 0.0]])
    return keypoints, np.full(count, 90.0)


@pytest.mark.parametrize("body_format", ["body_18", "body_34"])
def test_zed_bodies_map_onto_the_canonical_keypoints(body_format: str) -> None:
    rng = np.random.default_rng(1)
    canonical = skeleton(np.array([0.1, 0.0, 0.4, 0.2, 0.3, -0.2, 0.1, 0.5])) + (1.5, 0.2, 0.0)  # a person 1.5 m ahead
    keypoints, confidence = zed_body(body_format, canonical, rng)
    xyz, conf = zed_skeleton(keypoints, confidence, body_format, IDENTITY, MIN_CONFIDENCE)
    expected = canonical.copy()
    if body_format == "body_18":  # no pelvis keypoint: the hip centre
        expected[K["pelvis"]] = (canonical[K["left_hip"]] + canonical[K["right_hip"]]) / 2
    np.testing.assert_allclose(xyz, expected, atol=1e-12)
    np.testing.assert_allclose(conf, 0.9)


def test_zed_mapping_follows_the_sdk_orders() -> None:
    assert BODY_18["left_shoulder"] == (5,) and BODY_18["right_wrist"] == (4,) and BODY_18["pelvis"] == (8, 11)
    assert BODY_34["pelvis"] == (0,) and BODY_34["spine_chest"] == (3,) and BODY_34["head"] == (26,)
    assert BODY_34["left_wrist"] == (7,) and BODY_34["right_hip"] == (22,) and BODY_34["right_ankle"] == (24,)
    for count, mapping in BODY_FORMATS.values():
        assert set(mapping) == set(KEYPOINT_NAMES) and all(0 <= i < count for s in mapping.values() for i in s)


def test_zed_low_confidence_and_unseen_points_are_missing_and_extrinsics_apply() -> None:
    keypoints = np.tile(np.array([2.0, 0.0, 0.0]), (34, 1))
    confidence = np.full(34, 80.0)
    confidence[7] = 10.0  # left wrist barely seen
    keypoints[13] = np.nan  # right elbow unseen (the SDK's NaN)
    confidence[13] = np.nan
    camera = body_to_robot(CameraExtrinsics(position=[3.0, 0.0, 1.0], rpy=[0.0, 0.0, math.pi]))  # looks back at the robot
    xyz, conf = zed_skeleton(keypoints, confidence, "body_34", camera, MIN_CONFIDENCE)
    for name in ("left_wrist", "right_elbow"):
        assert np.isnan(xyz[K[name]]).all() and conf[K[name]] == 0.0
    np.testing.assert_allclose(xyz[K["pelvis"]], [1.0, 0.0, 1.0], atol=1e-12)  # 2 m ahead of a camera at x = 3
    assert conf[K["pelvis"]] == pytest.approx(0.8)
    with pytest.raises(ValueError, match="body_18"):
        zed_skeleton(keypoints, confidence, "body_18", camera, MIN_CONFIDENCE)


def test_zed_source_with_the_sdk() -> None:
    """Where pyzed is missing the source is a clear error and this test is skipped with the reason;
    with the SDK and a camera it streams canonical frames."""
    try:
        import pyzed.sl  # noqa: F401
    except ImportError as exc:
        with pytest.raises(SourceUnavailable, match="pyzed"):
            open_source(PerceptionConfig(source="zed"))
        pytest.skip(f"the ZED SDK's Python API is not installed here (import pyzed.sl: {exc})")
    try:
        source = open_source(PerceptionConfig(source="zed"))
    except SourceUnavailable as exc:
        pytest.skip(f"pyzed is installed but no ZED camera opens: {exc}")
    stop = threading.Event()
    frames = []
    for frame in source.frames(stop):
        frames.append(frame)
        if len(frames) == 5:
            stop.set()
    assert len(frames) == 5 and all(f.xyz.shape == (15, 3) and f.conf.shape == (15,) for f in frames)
