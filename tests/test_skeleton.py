"""The .npz recording format (architecture §6): read by name, any order, clear errors, round trip."""

from __future__ import annotations

import numpy as np
import pytest

from shared.names import KEYPOINT_INDEX, KEYPOINT_NAMES
from shared.skeleton import Recording, RecordingError, read_recording, write_recording
from tests.support.team import MOCAP_DIR


def standing_pose() -> np.ndarray:
    """(15, 3) a plausible standing person in metres (x forward, y left, z up)."""
    p = {
        "pelvis": (0, 0, 1.0), "spine_chest": (0, 0, 1.45), "head": (0, 0, 1.6),
        "left_shoulder": (0, 0.18, 1.4), "left_elbow": (0, 0.2, 1.12), "left_wrist": (0, 0.2, 0.88),
        "right_shoulder": (0, -0.18, 1.4), "right_elbow": (0, -0.2, 1.12), "right_wrist": (0, -0.2, 0.88),
        "left_hip": (0, 0.09, 0.95), "left_knee": (0, 0.09, 0.5), "left_ankle": (0, 0.09, 0.08),
        "right_hip": (0, -0.09, 0.95), "right_knee": (0, -0.09, 0.5), "right_ankle": (0, -0.09, 0.08),
    }
    return np.array([p[n] for n in KEYPOINT_NAMES], dtype=float)


def save(path, **arrays) -> None:
    np.savez(path, **arrays)


def test_reads_any_key_order_extra_keys_and_missing_optional(tmp_path) -> None:
    pose = standing_pose()
    order = list(reversed(KEYPOINT_NAMES))
    xyz = np.stack([pose[[KEYPOINT_INDEX[n] for n in order]]] * 4)
    save(tmp_path / "r.npz", xyz=xyz, fps=30.0, names=np.array(order), t=np.arange(4) / 30, extra=np.zeros(3))
    rec = read_recording(tmp_path / "r.npz")
    np.testing.assert_array_equal(rec.xyz[0], pose)
    assert rec.conf.shape == (4, 15) and (rec.conf == 1).all() and rec.source == ""
    assert rec.valid.all() and len(rec) == 4


def test_missing_keypoints_are_marked_not_invented(tmp_path) -> None:
    names = [n for n in KEYPOINT_NAMES if n != "head"]
    xyz = standing_pose()[[KEYPOINT_INDEX[n] for n in names]][None]
    xyz[0, 0] = np.nan  # pelvis lost in this frame
    save(tmp_path / "r.npz", names=np.array(names), t=np.array([0.0]), xyz=xyz, fps=30.0)
    rec = read_recording(tmp_path / "r.npz")
    assert not rec.valid[0, KEYPOINT_INDEX["head"]] and np.isnan(rec.xyz[0, KEYPOINT_INDEX["head"]]).all()
    assert not rec.valid[0, KEYPOINT_INDEX["pelvis"]]
    assert rec.valid[0].sum() == 13


@pytest.mark.parametrize(
    "change, message",
    [
        ({"xyz": np.zeros((3, 15, 2))}, "'xyz' must have shape"),
        ({"t": np.array([0.0, 0.1, 0.1])}, "strictly increasing"),
        ({"names": np.array(["pelvis"] * 15)}, "duplicate"),
        ({"names": np.array(["hips", *KEYPOINT_NAMES[1:]])}, "unknown keypoint names"),
        ({"xyz": np.stack([standing_pose() * 100] * 3)}, "units must be metres"),
        ({"xyz": np.stack([standing_pose() * 1000] * 3)}, "units must be metres"),
        ({"xyz": np.stack([standing_pose() + 500.0] * 3)}, "beyond 100.0 m"),
        ({"conf": np.full((3, 15), 2.0)}, "'conf' must lie in"),
        ({"fps": -1.0}, "'fps'"),
    ],
)
def test_bad_files_give_clear_errors(tmp_path, change, message) -> None:
    arrays = {"names": np.array(KEYPOINT_NAMES), "t": np.arange(3) / 30, "xyz": np.stack([standing_pose()] * 3), "fps": 30.0}
    arrays.update(change)
    save(tmp_path / "bad.npz", **arrays)
    with pytest.raises(RecordingError, match=message):
        read_recording(tmp_path / "bad.npz")


def test_missing_required_key_and_not_a_file(tmp_path) -> None:
    save(tmp_path / "r.npz", names=np.array(KEYPOINT_NAMES), t=np.zeros(1), fps=30.0)
    with pytest.raises(RecordingError, match="missing required key 'xyz'"):
        read_recording(tmp_path / "r.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(RecordingError, match="cannot read"):
        read_recording(tmp_path / "junk.npz")
    with pytest.raises(RecordingError, match="cannot read"):
        read_recording(tmp_path / "absent.npz")


def test_write_read_round_trip(tmp_path) -> None:
    rng = np.random.default_rng(1)
    xyz = standing_pose()[None] + rng.normal(scale=0.01, size=(10, 15, 3))
    xyz[3, 5] = np.nan
    conf = rng.uniform(0.1, 1, size=(10, 15))
    conf[3, 5] = 0
    rec = Recording(t=np.arange(10) / 30, xyz=xyz, conf=conf, fps=30.0, source="unit test")
    back = read_recording(write_recording(tmp_path / "sub" / "r.npz", rec))
    np.testing.assert_array_equal(back.xyz, rec.xyz)
    np.testing.assert_array_equal(back.conf, rec.conf)
    assert back.fps == 30.0 and back.source == "unit test"


def test_real_mocap_clips_read() -> None:
    clips = sorted(MOCAP_DIR.glob("*.npz"))
    if not clips:
        pytest.skip(f"team mocap clips not found in {MOCAP_DIR}")
    for clip in clips:
        rec = read_recording(clip)
        assert rec.valid.all() and rec.fps == 30.0
        upper_arm = np.linalg.norm(rec.xyz[:, KEYPOINT_INDEX["left_shoulder"]] - rec.xyz[:, KEYPOINT_INDEX["left_elbow"]], axis=-1)
        assert 0.2 < upper_arm.mean() < 0.3
