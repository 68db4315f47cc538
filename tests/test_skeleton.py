"""The .npz recording format (architecture §6): read by name, any order, clear errors, round trip."""

from __future__ import annotations

import numpy as np
import pytest

from shared.names import KEYPOINT_INDEX, KEYPOINT_NAMES
from shared.skeleton import Recording, RecordingError, read_recording, with_hip_centre_pelvis, write_recording
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
        ({"xyz": np.stack([standing_pose()[:, [0, 2, 1]] * (1, 1, -1)] * 3)}, "does not stand along z"),  # y up
        ({"xyz": np.stack([standing_pose() * (1, 1, -1)] * 3)}, "does not stand along z"),  # upside down
        ({"xyz": np.stack([standing_pose() * 0.01] * 3)}, "units must be metres"),  # a toy: never near the robot
        ({"xyz": np.full((3, 15, 3), np.nan)}, "no keypoint in any frame"),
        ({"conf": np.zeros((3, 15))}, "no keypoint in any frame"),
        ({"t": np.arange(3) / 30 * 1000}, "'t' must be in seconds"),  # milliseconds
        ({"t": np.arange(3) * 33_333_333}, "'t' must be in seconds"),  # integer nanoseconds
        ({"fps": 1.0}, "'fps' 1 means 1 s"),  # a wrong fps for 30 Hz times
        ({"valid": np.ones((3, 15), bool)}, "key 'valid' is not part of the format"),
        ({"mask": np.ones((3, 15), bool)}, "mark a missing keypoint with NaN in 'xyz' or 0 in 'conf'"),
    ],
)
def test_bad_files_give_clear_errors(tmp_path, change, message) -> None:
    arrays = {"names": np.array(KEYPOINT_NAMES), "t": np.arange(3) / 30, "xyz": np.stack([standing_pose()] * 3), "fps": 30.0}
    arrays.update(change)
    save(tmp_path / "bad.npz", **arrays)
    with pytest.raises(RecordingError, match=message):
        read_recording(tmp_path / "bad.npz")


def test_a_person_bending_or_lying_back_at_times_is_still_upright(tmp_path) -> None:
    """The z-up check takes the median frame: 4 of 10 frames with the torso horizontal (bent
    forward, then lying back) and a pelvis missing from the file altogether still read."""
    pose = standing_pose()
    lying = pose.copy()
    lying[:, [0, 2]] = pose[:, [2, 0]] - (1.0, 0.0)  # about y: the head along +x at z ≈ 0
    xyz = np.stack([pose] * 6 + [lying] * 4)
    names = [n for n in KEYPOINT_NAMES if n != "pelvis"]
    save(tmp_path / "r.npz", names=np.array(names), t=np.arange(10) / 30, fps=30.0,
         xyz=xyz[:, [KEYPOINT_INDEX[n] for n in names]])
    assert len(read_recording(tmp_path / "r.npz")) == 10


def test_the_pelvis_completion_is_the_hip_centre_only_where_it_is_missing() -> None:
    rng = np.random.default_rng(3)
    xyz = standing_pose()[None] + rng.normal(scale=0.02, size=(4, 15, 3))
    conf = rng.uniform(0.2, 1.0, size=(4, 15))
    pelvis, left, right = KEYPOINT_INDEX["pelvis"], KEYPOINT_INDEX["left_hip"], KEYPOINT_INDEX["right_hip"]
    xyz[1:, pelvis] = np.nan  # frames 1–3 without a pelvis; in frame 2 a hip is missing too, in 3 its confidence is 0
    xyz[2, left] = np.nan
    conf[3, right] = 0.0
    rec = Recording(t=np.arange(4) / 30, xyz=xyz, conf=conf, fps=30.0)
    done = with_hip_centre_pelvis(rec)
    np.testing.assert_array_equal(done.xyz[0], xyz[0])  # a pelvis present is kept
    np.testing.assert_allclose(done.xyz[1, pelvis], 0.5 * (xyz[1, left] + xyz[1, right]))
    assert done.conf[1, pelvis] == min(conf[1, left], conf[1, right]) and done.valid[1, pelvis]
    assert not done.valid[2, pelvis] and not done.valid[3, pelvis]  # never from one hip
    mask = np.ones(15, bool)
    mask[pelvis] = False
    np.testing.assert_array_equal(done.xyz[:, mask], xyz[:, mask])  # nothing else changes
    np.testing.assert_array_equal(done.conf[:, mask], conf[:, mask])
    assert np.isnan(rec.xyz[1, pelvis]).all()  # the input is not written
    assert with_hip_centre_pelvis(done) is done  # nothing left to complete


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
