"""Test variants of recordings: the same motion turned in place, carried into the robot, by a
taller or shorter person, or faster.

The development clips are four; the product meets other people doing other things (turns, walking,
someone stepping into the robot). ``safemimic variants SOURCE OUT`` (or ``python -m
safemimic.evaluate.variants SOURCE OUT``) writes, for every recording ``SOURCE/X.npz`` (the evaluator's
``names``/``t``/``xyz`` format, z up, metres), these variants into ``OUT`` with every other field
unchanged:

- ``X_turn.npz``: the whole skeleton rotated about the vertical through the first frame's pelvis by
  an angle growing linearly from 0 at the first frame to ``--turns`` · 2π at the last (a person
  turning in place while moving; one turn by default);
- ``X_stepin.npz``: the whole skeleton carried along the direction the person faces in the first
  frame (horizontal, (left shoulder − right shoulder) × z) by a distance growing linearly from 0 to
  ``--step-m`` (1 m by default) at the last frame: placed facing the robot, the person walks into it;
- ``X_sidestep.npz``: the same, carried towards the person's right (the facing direction turned
  −90° about z) by up to ``--side-m`` (0.5 m by default): placed side by side (the robot on the
  person's right, 0.70 m away) they step sideways into the robot; facing it, they walk across it;
- ``X_scaleNNN.npz`` for each factor s of ``--scales`` (0.85 and 1.15 by default; NNN = 100 s): the
  whole skeleton scaled by s about the floor point below the first frame's pelvis (a shorter or
  taller person doing the same motion: longer arms reach further, a taller body is closer to the
  robot's shoulders; the motion's speeds scale with it);
- ``X_mirror.npz``: the mirror image about the vertical plane through frame 0's pelvis along the
  direction the person faces, left and right keypoints swapped (the same motion by a left-handed
  person: side by side, the arm that punches or slashes is now the one beside the robot);
- ``X_shouldersNNNmm.npz`` (``--shoulder-width``, 0.37 m by default; NNN in mm): each arm
  (shoulder, elbow, wrist) carried outward along the frame's shoulder line so that the shoulders
  are that far apart in every frame, everything else unchanged (a broader person, or a skeleton
  whose shoulder keypoints sit further out, making the same motion: people's shoulders are
  0.20–0.37 m apart, the development clips' 0.20 m; beside the robot the near arm comes closer);
- ``X_fastNNN.npz`` for each factor s of ``--speeds`` (1.5 by default; NNN = 100 s): the same motion
  s times as fast, at the recording's own frame rate — frame k is the skeleton at s·k frame periods
  of the original, interpolated linearly between its frames (a keypoint missing in either frame is
  missing; every per-frame field likewise), so the clip lasts 1/s as long. A person faster than the
  one recorded: the development clips' fastest wrists reach 5.1–5.2 m/s, a trained person's punch
  7–10 m/s.

Then ``safemimic evaluate --suite OUT`` evaluates them like any recording. The variants are
geometric transforms of real motion, not new recordings: they test what the development clips do
not show (a person's back to the camera, a body moving through the robot), never a constant's value.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from shared.cli_args import check_output_path
from shared.entrypoint import ParagraphHelpFormatter
from shared.skeleton import read_npz

#: Keypoints a variant needs: the pelvis (turn axis) and the shoulders (facing direction).
NEEDED = ("pelvis", "left_shoulder", "right_shoulder")
#: The size factors of the scaled variants (``--scales``): a 15 % shorter and a 15 % taller person.
SCALES = (0.85, 1.15)
#: Default factors of the faster variants (``--speeds``).
SPEEDS = (1.5,)
#: The shoulder width of the broadened variant (``--shoulder-width``, m): the broadest people's.
BROAD_SHOULDERS = 0.37
#: Each arm's keypoints, carried with its shoulder by :func:`broadened`.
ARMS = {side: tuple(f"{side}_{part}" for part in ("shoulder", "elbow", "wrist")) for side in ("left", "right")}


def facing(xyz: np.ndarray, names: list[str]) -> np.ndarray:
    """The horizontal unit vector the person faces in frame ``xyz`` (K, 3): (left − right shoulder) × z."""
    lateral = xyz[names.index("left_shoulder")] - xyz[names.index("right_shoulder")]
    forward = np.cross(lateral, [0.0, 0.0, 1.0])  # horizontal: the cross product with z has no z component
    norm = float(np.linalg.norm(forward))
    if not norm > 1e-6:
        raise ValueError("the first frame's shoulders are on top of each other: no facing direction")
    return forward / norm


def floor_below_pelvis(xyz: np.ndarray, names: list[str]) -> np.ndarray:
    """(3,) the floor point (z = 0) below frame 0's pelvis of ``xyz`` (T, K, 3)."""
    centre = xyz[0, names.index("pelvis")].copy()
    centre[2] = 0.0
    return centre


def turned(xyz: np.ndarray, names: list[str], turns: float = 1.0) -> np.ndarray:
    """``xyz`` (T, K, 3) rotated about the vertical through frame 0's pelvis by 2π · turns · k / (T − 1) at frame k."""
    centre = floor_below_pelvis(xyz, names)
    angle = 2.0 * np.pi * turns * np.linspace(0.0, 1.0, len(xyz))
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    rel = xyz - centre
    out = np.empty_like(xyz)
    out[..., 0] = c * rel[..., 0] - s * rel[..., 1]
    out[..., 1] = s * rel[..., 0] + c * rel[..., 1]
    out[..., 2] = rel[..., 2]
    return out + centre


def stepped_in(xyz: np.ndarray, names: list[str], step_m: float = 1.0) -> np.ndarray:
    """``xyz`` (T, K, 3) carried along frame 0's facing direction by step_m · k / (T − 1) at frame k."""
    return xyz + np.linspace(0.0, step_m, len(xyz))[:, None, None] * facing(xyz[0], names)


def side_stepped(xyz: np.ndarray, names: list[str], side_m: float = 0.5) -> np.ndarray:
    """``xyz`` (T, K, 3) carried towards frame 0's right (the facing direction turned −90°
    about z) by side_m · k / (T − 1) at frame k."""
    right = np.cross(facing(xyz[0], names), [0.0, 0.0, 1.0])
    return xyz + np.linspace(0.0, side_m, len(xyz))[:, None, None] * right


def mirror_order(names: list[str]) -> np.ndarray:
    """(K,) for each keypoint the index of its mirror image in ``names``: left_X ↔ right_X (itself
    when it has no side or its other side is missing)."""
    def index_of_other(i: int, name: str) -> int:
        for a, b in (("left_", "right_"), ("right_", "left_")):
            if name.startswith(a) and b + name.removeprefix(a) in names:
                return names.index(b + name.removeprefix(a))
        return i
    return np.array([index_of_other(i, n) for i, n in enumerate(names)])


def mirrored(xyz: np.ndarray, names: list[str]) -> np.ndarray:
    """``xyz`` (T, K, 3) reflected about the vertical plane through frame 0's pelvis that contains
    frame 0's facing direction, its keypoints reordered by :func:`mirror_order` (a left-handed
    person: the reflected left shoulder, now on the right, is the right shoulder)."""
    left = np.cross([0.0, 0.0, 1.0], facing(xyz[0], names))  # horizontal unit: z × forward
    offset = (xyz - floor_below_pelvis(xyz, names)) @ left
    return (xyz - 2.0 * offset[..., None] * left)[:, mirror_order(names)]


def scaled(xyz: np.ndarray, names: list[str], factor: float) -> np.ndarray:
    """``xyz`` (T, K, 3) scaled by ``factor`` about the floor point (z = 0) below frame 0's pelvis."""
    if not factor > 0.0:
        raise ValueError(f"a scale must be > 0, got {factor}")
    centre = floor_below_pelvis(xyz, names)
    return centre + factor * (xyz - centre)


def broadened(xyz: np.ndarray, names: list[str], width: float) -> np.ndarray:
    """``xyz`` (T, K, 3) with the shoulders ``width`` (m) apart in every frame: each arm's keypoints
    (:data:`ARMS`) carried by ½ (width − w) along the frame's shoulder line (left − right, of length
    w), the left arm towards the left, the right arm towards the right. Arm segments keep their
    vectors; a frame without both shoulders (or with them on top of each other) is left as it is."""
    if not width > 0.0:
        raise ValueError(f"a shoulder width must be > 0, got {width}")
    line = xyz[:, names.index("left_shoulder")] - xyz[:, names.index("right_shoulder")]
    w = np.linalg.norm(line, axis=1, keepdims=True)
    usable = np.isfinite(w) & (w > 1e-6)
    shift = np.where(usable, 0.5 * (width - w) * line / np.where(usable, w, 1.0), 0.0)
    out = xyz.copy()
    for side, sign in (("left", 1.0), ("right", -1.0)):
        for name in ARMS[side]:
            if name in names:
                out[:, names.index(name)] += sign * shift
    return out


def quickened(fields: dict[str, np.ndarray], factor: float) -> dict[str, np.ndarray]:
    """Recording ``fields`` played ``factor`` (> 0) times as fast, resampled at its own ``fps`` (module
    docstring): ``t`` k / fps from the first frame; every other array with one row per frame
    interpolated linearly in the original time at ``t[0]`` + factor · k / fps (NaN where either
    neighbour is; integer and boolean fields take the earlier frame's); the rest unchanged."""
    if not (factor > 0.0 and np.isfinite(factor)):
        raise ValueError(f"a speed factor must be finite and > 0, got {factor}")
    if "t" not in fields or "fps" not in fields:
        raise ValueError("a faster variant needs the recording's 't' and 'fps' (--speeds '' for none)")
    t = np.asarray(fields["t"], dtype=np.float64)
    fps = float(np.asarray(fields["fps"]).reshape(()))
    count = int(np.floor((t[-1] - t[0]) * fps / factor + 1e-9)) + 1
    source_t = t[0] + factor * np.arange(count) / fps
    before = np.clip(np.searchsorted(t, source_t, side="right") - 1, 0, len(t) - 1)
    after = np.minimum(before + 1, len(t) - 1)
    span = t[after] - t[before]
    weight = np.where(span > 0.0, (source_t - t[before]) / np.where(span > 0.0, span, 1.0), 0.0)
    out = dict(fields)
    out["t"] = t[0] + np.arange(count) / fps
    for key, value in fields.items():
        if key == "t" or np.ndim(value) == 0 or len(value) != len(t):
            continue
        if not np.issubdtype(value.dtype, np.floating):
            out[key] = value[before]
            continue
        w = weight.reshape((-1,) + (1,) * (value.ndim - 1))
        mixed = (1.0 - w) * value[before] + w * value[after]
        out[key] = np.where(w == 0.0, value[before], mixed)
    return out


def read_recording(path: Path) -> tuple[dict[str, np.ndarray], list[str]]:
    """Every field of recording ``path`` and its keypoint names; ValueError when it cannot make variants
    (:class:`~shared.skeleton.RecordingError` when it is no ``.npz`` at all)."""
    fields = read_npz(path)
    if "xyz" not in fields or "names" not in fields:
        raise ValueError(f"{path}: not a recording (needs 'names' and 'xyz')")
    names = [str(n) for n in fields["names"]]
    xyz = np.asarray(fields["xyz"], dtype=np.float64)
    if xyz.ndim != 3 or xyz.shape[1:] != (len(names), 3) or len(xyz) < 2:
        raise ValueError(f"{path}: xyz must be (frames ≥ 2, {len(names)}, 3), got {xyz.shape}")
    missing = [n for n in NEEDED if n not in names]
    if missing:
        raise ValueError(f"{path}: no {', '.join(missing)} keypoint")
    if not np.isfinite(xyz[0, [names.index(n) for n in NEEDED]]).all():
        raise ValueError(f"{path}: the first frame's pelvis and shoulders must be finite")
    fields["xyz"] = xyz
    return fields, names


def variants(xyz: np.ndarray, names: list[str], turns: float = 1.0, step_m: float = 1.0, side_m: float = 0.5,
             scales: tuple[float, ...] = SCALES, shoulder_width: float = BROAD_SHOULDERS) -> dict[str, np.ndarray]:
    """Every variant of ``xyz`` (T, K, 3) by its file name suffix (module docstring); no broadened
    variant when ``shoulder_width`` is 0."""
    out = {"turn": turned(xyz, names, turns), "stepin": stepped_in(xyz, names, step_m),
           "sidestep": side_stepped(xyz, names, side_m), "mirror": mirrored(xyz, names)}
    for factor in scales:
        out[f"scale{round(100 * factor):03d}"] = scaled(xyz, names, factor)
    if shoulder_width:
        out[f"shoulders{round(1000 * shoulder_width):03d}mm"] = broadened(xyz, names, shoulder_width)
    return out


def write_variants(source: Path, out: Path, turns: float = 1.0, step_m: float = 1.0, side_m: float = 0.5,
                   scales: tuple[float, ...] = SCALES, shoulder_width: float = BROAD_SHOULDERS,
                   speeds: tuple[float, ...] = SPEEDS) -> list[Path]:
    """The variants of recording ``source`` written into ``out``; their paths."""
    fields, names = read_recording(source)
    written = []
    for factor in speeds:
        path = out / f"{source.stem}_fast{round(100 * factor):03d}.npz"
        np.savez(path, **quickened(fields, factor))
        written.append(path)
    for suffix, xyz in variants(fields["xyz"], names, turns, step_m, side_m, scales, shoulder_width).items():
        path = out / f"{source.stem}_{suffix}.npz"
        conf = fields.get("conf")
        sides = suffix == "mirror" and conf is not None and conf.ndim == 2 and conf.shape[1] == len(names)
        conf = {"conf": conf[:, mirror_order(names)]} if sides else {}
        np.savez(path, **{**fields, "xyz": xyz, **conf})
        written.append(path)
    return written


def _factors(text: str) -> tuple[float, ...]:
    """``--scales``, ``--speeds``: comma-separated positive factors (argparse type)."""
    try:
        factors = tuple(float(part) for part in text.split(",") if part.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a list of numbers: {text!r}") from None
    if not all(f > 0.0 and np.isfinite(f) for f in factors):
        raise argparse.ArgumentTypeError(f"factors must be finite and > 0: {text!r}")
    return factors


def _width(text: str) -> float:
    """``--shoulder-width``: 0 (no broadened variant) or a width in (0, 1) m (argparse type)."""
    try:
        width = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not 0.0 <= width < 1.0:
        raise argparse.ArgumentTypeError(f"a shoulder width must be 0 (none) or in (0, 1) m: {text!r}")
    return width


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic variants")
    parser.formatter_class = ParagraphHelpFormatter
    parser.description = (
        "Test variants of skeleton recordings, to evaluate with 'safemimic evaluate --suite OUT': for each "
        "recording X.npz in SOURCE (a .npz file or a folder of them) the same motion written into OUT turned in "
        "place (X_turn.npz, --turns), walking forward (X_stepin.npz, --step-m), stepping towards the person's "
        "right (X_sidestep.npz, --side-m), by a shorter or taller person (X_scaleNNN.npz, --scales), mirrored as "
        "by a left-handed person (X_mirror.npz), with broader shoulders (X_shouldersNNNmm.npz, --shoulder-width) "
        "and faster (X_fastNNN.npz, --speeds); every other field of the file is unchanged.\n\n"
        "Placed facing the robot, the person who walks forward walks into it; placed side by side, the one who "
        "steps right steps into it. The variants are geometric transforms of real motion, not new recordings: "
        "they test what the recordings do not show.\n\n"
        "  safemimic variants clips/ variants/\n"
        "  safemimic evaluate --suite variants/ --jobs 2 --out variants-eval"
    )
    parser.add_argument("source", type=Path, metavar="SOURCE", help="a recording (.npz) or a folder of them")
    parser.add_argument("out", type=Path, metavar="OUT", help="folder for the variants (created)")
    parser.add_argument("--turns", type=float, default=1.0, metavar="N",
                        help="full turns in place over the clip (default 1)")
    parser.add_argument("--step-m", type=float, default=1.0, metavar="M",
                        help="distance walked forward over the clip, m (default 1)")
    parser.add_argument("--side-m", type=float, default=0.5, metavar="M",
                        help="distance stepped towards the person's right over the clip, m (default 0.5)")
    parser.add_argument("--scales", type=_factors, default=SCALES, metavar="LIST",
                        help="comma-separated size factors of the scaled variants (default "
                        f"{','.join(map(str, SCALES))}; '' for none)")
    parser.add_argument("--shoulder-width", type=_width, default=BROAD_SHOULDERS, metavar="M",
                        help=f"shoulder width of the broadened variant, m (default {BROAD_SHOULDERS}; 0 for none)")
    parser.add_argument("--speeds", type=_factors, default=SPEEDS, metavar="LIST",
                        help="comma-separated speed factors of the faster variants (default "
                        f"{','.join(map(str, SPEEDS))}; '' for none)")
    return parser


def run(args: argparse.Namespace) -> int:
    """Write the variants of every recording named; 2 (and a message) for unusable input."""
    if not args.source.exists():
        print(f"error: no such recording or folder: {args.source}", file=sys.stderr)
        return 2
    sources = sorted(args.source.glob("*.npz")) if args.source.is_dir() else [args.source]
    if not sources:
        print(f"error: no .npz recording in {args.source}", file=sys.stderr)
        return 2
    try:
        check_output_path(args.out, "OUT", folder=True)
        args.out.mkdir(parents=True, exist_ok=True)
        for source in sources:
            for path in write_variants(source, args.out, args.turns, args.step_m, args.side_m, args.scales,
                                       args.shoulder_width, args.speeds):
                print(f"wrote {path}")
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m safemimic.evaluate.variants``: the same as ``safemimic variants``."""
    return run(build_parser(argparse.ArgumentParser(prog="python -m safemimic.evaluate.variants")).parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
