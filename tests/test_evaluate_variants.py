"""Test variants of a recording (``safemimic variants``, ``python -m safemimic.evaluate.variants``): a turn in place keeps
every keypoint's height and distance from the turning axis and ends where it began, a step-in
carries the person along the direction they face by exactly the step, a side-step towards their
right, a scaled person keeps the floor point below the pelvis and scales every distance, a broadened
one has its shoulders the width apart and its arms' segments unchanged, a mirrored one is the
reflection with left and right swapped, a faster one is the same motion sooner at the same frame
rate; bad input is refused; the ``safemimic`` command runs it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from safemimic.cli import main as safemimic
from safemimic.evaluate.variants import main, mirrored, read_recording
from shared.names import KEYPOINT_INDEX, KEYPOINT_NAMES
from tests.test_evaluate_truth import raise_recording, write_recording

PELVIS = KEYPOINT_INDEX["pelvis"]


def test_a_turn_keeps_heights_and_radii_and_a_step_in_walks_where_the_person_faces(tmp_path: Path) -> None:
    xyz = raise_recording(2.0)
    xyz += [0.3, -0.2, 0.0]  # off the origin: the axis is the first pelvis, not the world's
    source = write_recording(tmp_path / "raise.npz", xyz)
    assert main([str(source), str(tmp_path / "out"), "--step-m", "0.8"]) == 0
    turn, _ = read_recording(tmp_path / "out" / "raise_turn.npz")
    step, _ = read_recording(tmp_path / "out" / "raise_stepin.npz")
    axis = xyz[0, PELVIS, :2]
    radius = np.linalg.norm(xyz[..., :2] - axis, axis=-1)
    np.testing.assert_allclose(np.linalg.norm(turn["xyz"][..., :2] - axis, axis=-1), radius, atol=1e-9)
    np.testing.assert_allclose(turn["xyz"][..., 2], xyz[..., 2], atol=1e-12)
    np.testing.assert_allclose(turn["xyz"][[0, -1]], xyz[[0, -1]], atol=1e-9)  # 0 and one full turn
    half = len(xyz) // 2
    angle = 2.0 * np.pi * half / (len(xyz) - 1)
    wrist = KEYPOINT_INDEX["left_wrist"]
    before, after = xyz[half, wrist, :2] - axis, turn["xyz"][half, wrist, :2] - axis
    turned_by = np.arctan2(before[0] * after[1] - before[1] * after[0], before @ after)
    assert turned_by % (2 * np.pi) == pytest.approx(angle % (2 * np.pi), abs=1e-9)
    shift = step["xyz"][-1] - xyz[-1]
    np.testing.assert_allclose(shift, np.repeat(shift[:1], len(KEYPOINT_NAMES), axis=0), atol=1e-12)  # rigid
    left, right = xyz[0, KEYPOINT_INDEX["left_shoulder"]], xyz[0, KEYPOINT_INDEX["right_shoulder"]]
    assert np.linalg.norm(shift[0]) == pytest.approx(0.8) and shift[0, 2] == 0.0
    assert shift[0] @ np.cross(left - right, [0.0, 0.0, 1.0]) > 0  # forward: left × up, away from the back
    for key in ("t", "names", "fps", "conf"):
        np.testing.assert_array_equal(turn[key], np.load(source)[key])


def test_a_side_step_goes_right_and_a_scaled_person_grows_about_the_floor_below_the_pelvis(tmp_path: Path) -> None:
    xyz = raise_recording(2.0) + [0.3, -0.2, 0.0]
    source = write_recording(tmp_path / "raise.npz", xyz)
    assert main([str(source), str(tmp_path / "out"), "--side-m", "0.4", "--scales", "0.8,1.25"]) == 0
    written = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert written == ["raise_fast150.npz", "raise_mirror.npz", "raise_scale080.npz", "raise_scale125.npz",
                       "raise_shoulders370mm.npz", "raise_sidestep.npz", "raise_stepin.npz", "raise_turn.npz"]
    side, _ = read_recording(tmp_path / "out" / "raise_sidestep.npz")
    shift = side["xyz"][-1] - xyz[-1]
    np.testing.assert_allclose(shift, np.repeat(shift[:1], len(KEYPOINT_NAMES), axis=0), atol=1e-12)  # rigid
    left, right = xyz[0, KEYPOINT_INDEX["left_shoulder"]], xyz[0, KEYPOINT_INDEX["right_shoulder"]]
    lateral = (left - right)[:2] / np.linalg.norm((left - right)[:2])
    assert np.linalg.norm(shift[0]) == pytest.approx(0.4) and shift[0, 2] == 0.0
    assert shift[0, :2] @ lateral == pytest.approx(-0.4, abs=1e-9)  # all of it towards the right
    foot = np.array([*xyz[0, PELVIS, :2], 0.0])
    for name, factor in (("raise_scale080.npz", 0.8), ("raise_scale125.npz", 1.25)):
        big, _ = read_recording(tmp_path / "out" / name)
        np.testing.assert_allclose(big["xyz"] - foot, factor * (xyz - foot), atol=1e-12)
        assert big["xyz"][0, PELVIS, :2] == pytest.approx(xyz[0, PELVIS, :2])  # stands where the person stood
        np.testing.assert_allclose(big["xyz"][..., 2], factor * xyz[..., 2], atol=1e-12)  # the floor stays z = 0
    assert main([str(source), str(tmp_path / "none"), "--scales", ""]) == 0
    assert not list((tmp_path / "none").glob("*_scale*"))


def test_a_broadened_or_narrowed_person_has_the_shoulders_the_width_apart_and_the_same_arms_and_body(tmp_path: Path) -> None:
    xyz = raise_recording(2.0) + [0.3, -0.2, 0.0]
    xyz[5, KEYPOINT_INDEX["right_shoulder"]] = np.nan  # a frame without its shoulder line: left as it is
    source = write_recording(tmp_path / "raise.npz", xyz)
    assert main([str(source), str(tmp_path / "out"), "--shoulder-width", "0.25"]) == 0
    broad, _ = read_recording(tmp_path / "out" / "raise_shoulders250mm.npz")
    out = broad["xyz"]
    left, right = (KEYPOINT_INDEX[f"{side}_shoulder"] for side in ("left", "right"))
    seen = np.isfinite(xyz[:, right, 0])
    np.testing.assert_allclose(np.linalg.norm(out[seen, left] - out[seen, right], axis=1), 0.25, atol=1e-12)
    before = np.linalg.norm(xyz[seen, left] - xyz[seen, right], axis=1)
    assert before.min() > 0.25 + 0.05  # the synthetic person is broader (0.36 m): the variant does something
    centre = 0.5 * (xyz[seen, left] + xyz[seen, right])
    np.testing.assert_allclose(0.5 * (out[seen, left] + out[seen, right]), centre, atol=1e-12)  # outward, both alike
    for side in ("left", "right"):
        chain = [KEYPOINT_INDEX[f"{side}_{part}"] for part in ("shoulder", "elbow", "wrist")]
        np.testing.assert_allclose(np.diff(out[:, chain], axis=1), np.diff(xyz[:, chain], axis=1), atol=1e-12)
    others = [i for i, name in enumerate(KEYPOINT_NAMES) if not name.endswith(("shoulder", "elbow", "wrist"))]
    np.testing.assert_array_equal(out[:, others], xyz[:, others])
    np.testing.assert_array_equal(out[5], xyz[5])
    assert main([str(source), str(tmp_path / "none"), "--shoulder-width", "0"]) == 0
    assert not list((tmp_path / "none").glob("*_shoulders*"))


def test_a_mirrored_person_is_the_reflection_with_left_and_right_swapped(tmp_path: Path) -> None:
    xyz = raise_recording(2.0) + [0.3, -0.2, 0.0]
    conf = np.tile(np.linspace(0.5, 1.0, len(KEYPOINT_NAMES)), (len(xyz), 1))
    source = tmp_path / "raise.npz"
    np.savez(source, names=np.array(KEYPOINT_NAMES), t=np.arange(len(xyz)) / 30.0, xyz=xyz, fps=np.float64(30.0),
             conf=conf)
    assert main([str(source), str(tmp_path / "out")]) == 0
    mirror, names = read_recording(tmp_path / "out" / "raise_mirror.npz")
    out = mirror["xyz"]
    left, right = (KEYPOINT_INDEX[f"{side}_wrist"] for side in ("left", "right"))
    pelvis = xyz[0, PELVIS]
    lateral = xyz[0, KEYPOINT_INDEX["left_shoulder"], :2] - xyz[0, KEYPOINT_INDEX["right_shoulder"], :2]
    lateral /= np.linalg.norm(lateral)
    # the left wrist becomes the right one: at its height, as far to the right as it was to the left
    np.testing.assert_allclose(out[:, right, 2], xyz[:, left, 2], atol=1e-12)
    np.testing.assert_allclose((out[:, right, :2] - pelvis[:2]) @ lateral, -(xyz[:, left, :2] - pelvis[:2]) @ lateral,
                               atol=1e-12)
    np.testing.assert_allclose(out[:, PELVIS, 2], xyz[:, PELVIS, 2], atol=1e-12)
    np.testing.assert_allclose(out[0, PELVIS], pelvis, atol=1e-12)
    mirrored_lateral = out[0, KEYPOINT_INDEX["left_shoulder"], :2] - out[0, KEYPOINT_INDEX["right_shoulder"], :2]
    assert mirrored_lateral @ lateral > 0  # still facing the same way: left is left
    np.testing.assert_allclose(mirrored(out, names), xyz, atol=1e-12)  # twice is the original
    np.testing.assert_array_equal(mirror["conf"][:, left], conf[:, right])
    np.testing.assert_array_equal(mirror["conf"][:, PELVIS], conf[:, PELVIS])


def test_a_faster_person_makes_the_same_motion_sooner_at_the_same_frame_rate(tmp_path: Path) -> None:
    xyz = raise_recording(2.0) + [0.3, -0.2, 0.0]
    xyz[7, KEYPOINT_INDEX["left_wrist"]] = np.nan  # a keypoint missing in one frame
    conf = np.tile(np.linspace(0.5, 1.0, len(xyz))[:, None], (1, len(KEYPOINT_NAMES)))
    source = tmp_path / "raise.npz"
    np.savez(source, names=np.array(KEYPOINT_NAMES), t=0.5 + np.arange(len(xyz)) / 30.0, xyz=xyz,
             fps=np.float64(30.0), conf=conf, motion=np.str_("raise"))
    assert main([str(source), str(tmp_path / "out"), "--speeds", "1.5,2"]) == 0
    fast, _ = read_recording(tmp_path / "out" / "raise_fast150.npz")
    # 60 frames (0 … 59) at 1.5×: frames 0 … 39, frame k at original frame 1.5 k
    assert len(fast["t"]) == 40 and float(fast["fps"]) == 30.0 and str(fast["motion"]) == "raise"
    np.testing.assert_allclose(fast["t"], 0.5 + np.arange(40) / 30.0, atol=1e-12)
    even = np.arange(0, 40, 2)
    np.testing.assert_array_equal(fast["xyz"][even], xyz[3 * even // 2])  # exactly the original frames
    np.testing.assert_allclose(fast["xyz"][1], 0.5 * (xyz[1] + xyz[2]), atol=1e-12)  # between two frames
    np.testing.assert_allclose(fast["conf"][1], 0.5 * (conf[1] + conf[2]), atol=1e-12)
    wrist = KEYPOINT_INDEX["left_wrist"]
    # frame 7 is missing, and so is frame 5, made from it and frame 8 (1.5 × 5 = 7.5)
    assert np.isnan(fast["xyz"][5, wrist]).all() and np.isfinite(fast["xyz"][[4, 6], wrist]).all()
    twice, _ = read_recording(tmp_path / "out" / "raise_fast200.npz")
    np.testing.assert_array_equal(twice["xyz"], xyz[::2])
    speed = np.nanmax(np.linalg.norm(np.diff(twice["xyz"][:, wrist], axis=0), axis=-1))
    assert speed == pytest.approx(np.nanmax(np.linalg.norm(xyz[2::2, wrist] - xyz[:-2:2, wrist], axis=-1)))
    assert main([str(source), str(tmp_path / "none"), "--speeds", ""]) == 0
    assert not list((tmp_path / "none").glob("*_fast*"))
    np.savez(tmp_path / "untimed.npz", names=np.array(KEYPOINT_NAMES), xyz=xyz)
    assert main([str(tmp_path / "untimed.npz"), str(tmp_path / "untimed")]) == 2  # a clear error, no traceback


def test_variants_refuse_what_is_not_a_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    np.savez(tmp_path / "bad.npz", names=np.array(["head"]), xyz=np.zeros((3, 1, 3)))
    assert main([str(tmp_path / "bad.npz"), str(tmp_path / "out")]) == 2
    assert "no pelvis, left_shoulder, right_shoulder keypoint" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main([str(tmp_path / "empty"), str(tmp_path / "out")]) == 2
    assert "no .npz recording" in capsys.readouterr().err
    for bad in ("0.9,-1", "big", "nan"):
        with pytest.raises(SystemExit) as exit_:
            main([str(tmp_path / "bad.npz"), str(tmp_path / "out"), "--scales", bad])
        assert exit_.value.code == 2
        assert "argument --scales" in capsys.readouterr().err
    for bad in ("0", "fast", "inf"):
        with pytest.raises(SystemExit) as exit_:
            main([str(tmp_path / "bad.npz"), str(tmp_path / "out"), "--speeds", bad])
        assert exit_.value.code == 2
        assert "speeds" in capsys.readouterr().err
    for bad in ("-0.3", "2", "wide", "nan"):
        with pytest.raises(SystemExit) as exit_:
            main([str(tmp_path / "bad.npz"), str(tmp_path / "out"), "--shoulder-width", bad])
        assert exit_.value.code == 2
        assert "shoulder" in capsys.readouterr().err


def test_the_safemimic_command_writes_every_variant_of_a_folder(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    clips = tmp_path / "clips"
    clips.mkdir()
    for name in ("a", "b"):
        write_recording(clips / f"{name}.npz", raise_recording(1.0))
    assert safemimic(["variants", str(clips), str(tmp_path / "out"), "--scales", "1.1"]) == 0
    kinds = ["fast150", "mirror", "scale110", "shoulders370mm", "sidestep", "stepin", "turn"]
    written = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert written == sorted(f"{name}_{kind}.npz" for name in ("a", "b") for kind in kinds)
    assert capsys.readouterr().out.count("wrote ") == len(written)
    assert safemimic(["variants", str(tmp_path / "missing"), str(tmp_path / "elsewhere")]) == 2
    assert "no such recording or folder" in capsys.readouterr().err
    assert not (tmp_path / "elsewhere").exists()  # nothing written for a source that is not there
