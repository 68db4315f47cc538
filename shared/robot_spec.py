"""Robot description: the YAML file that tells the product which robot it drives.

A robot spec (``config/robots/*.yaml``) names the kinematic model (MJCF or URDF),
the 8 imitation joints (paper §II-B, in the paper's order), the home
configuration, optional joint-limit overrides, the 7 robot capsules of the
paper's collision model (§III-A) and the default self-collision pairs.

This module only validates the file's own content (types, names, shapes,
radii, pair references). Whether the joints and frames exist in the model is
checked when the kinematics are built (``services.safety.kinematics``), since
that needs Pinocchio and this module must stay importable on the camera PC.

Example::

    spec = load_robot_spec("config/robots/g1.yaml")
    spec.model            # absolute path of the MJCF, resolved against the YAML's folder
"""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from shared.config import CONFIG_DIR, ExecutorBackend, G1Mode, StackConfig, resolve_config_path
from shared.errors import SafemimicError
from shared.names import CAPSULE_NAMES, IMITATION_JOINT_NAMES

__all__ = [
    "CAPSULE_NAMES",
    "DEFAULT_SELF_PAIRS",
    "G1_IMITATION_JOINTS",
    "CapsuleSpec",
    "RobotSpec",
    "RobotSpecError",
    "default_robot_spec_path",
    "load_robot_spec",
]

# CAPSULE_NAMES (re-exported from shared.names): the seven robot capsules of the paper
# (§III-A), in the order every capsule array uses.

#: The paper's imitation joints q = [q_wr, q_wp, q_sp^L, q_sr^L, q_e^L, q_sp^R, q_sr^R, q_e^R]
#: with their Unitree G1 names (``shared.names.IMITATION_JOINT_NAMES``); θ index i drives joint i.
G1_IMITATION_JOINTS: tuple[str, ...] = IMITATION_JOINT_NAMES

#: Default robot self-collision pairs (14). Adjacent links are left out because their
#: capsules overlap at the shared joint by construction: upper arm–torso (the upper arm
#: hangs from the torso's shoulder), forearm–upper arm of the same arm (elbow), and
#: torso–thigh (both attached to the pelvis). Kept: forearms vs torso, every arm capsule
#: vs both thighs, and every left-arm capsule vs every right-arm capsule.
DEFAULT_SELF_PAIRS: tuple[tuple[str, str], ...] = (
    ("left_forearm", "torso"),
    ("right_forearm", "torso"),
    ("left_upper_arm", "left_thigh"),
    ("left_forearm", "left_thigh"),
    ("left_upper_arm", "right_thigh"),
    ("left_forearm", "right_thigh"),
    ("right_upper_arm", "left_thigh"),
    ("right_forearm", "left_thigh"),
    ("right_upper_arm", "right_thigh"),
    ("right_forearm", "right_thigh"),
    ("left_upper_arm", "right_upper_arm"),
    ("left_upper_arm", "right_forearm"),
    ("left_forearm", "right_upper_arm"),
    ("left_forearm", "right_forearm"),
)


class RobotSpecError(SafemimicError, ValueError):
    """A robot spec file is missing, unreadable or invalid (message names the file)."""


def _finite(value: float, what: str) -> float:
    if not math.isfinite(value):
        raise ValueError(f"{what} must be finite, got {value}")
    return value


class CapsuleSpec(BaseModel):
    """One robot capsule: segment ``[a, b]`` fixed in body/frame ``frame``, swept by ``radius``.

    ``a`` and ``b`` are expressed in that frame (metres); ``radius`` is in metres.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    frame: str = Field(min_length=1, description="body or frame name of the kinematic model")
    a: tuple[float, float, float]
    b: tuple[float, float, float]
    radius: float = Field(gt=0.0, le=1.0, description="capsule radius (m)")


class RobotSpec(BaseModel):
    """The robot description the product uses (``config/robots/*.yaml``)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    name: str = Field(min_length=1)
    model: str = Field(
        min_length=1,
        description="MJCF (.xml/.mjcf) or URDF (.urdf) path; relative paths are resolved "
        "against the spec file's folder by load_robot_spec",
    )
    base_body: str = Field(default="pelvis", min_length=1)
    base_height: float = Field(gt=0.0, le=5.0, description="height of base_body above the ground (m)")
    imitation_joints: list[str] = Field(
        description="the 8 imitated joints in the paper's order: waist roll, waist pitch, "
        "left shoulder pitch, left shoulder roll, left elbow, right shoulder pitch, "
        "right shoulder roll, right elbow"
    )
    home: dict[str, float] = Field(
        default_factory=dict, description="joint -> home angle (rad); unspecified joints are 0"
    )
    limits: dict[str, tuple[float, float]] = Field(
        default_factory=dict,
        description="imitation joint -> (min, max) (rad), overriding (tightening) the model's range",
    )
    joint_velocity_limits: dict[str, float] = Field(
        default_factory=dict,
        description="imitation joint -> the robot's velocity limit (rad/s, > 0; the manufacturer's description); "
        "safety.u_max and u_min must stay within it; unlisted: no limit known",
    )
    joint_barriers: dict[str, tuple[float | None, float | None]] = Field(
        default_factory=dict,
        description="imitation joint -> (lower, upper) (rad; null: none) kept by the CBF as joint-space "
        "barriers h = q - lower >= 0, h = upper - q >= 0: contacts between links the capsules cannot "
        "see (the upper arm and the torso capsules overlap at the shoulder by construction); unlike "
        "limits, the retargeted target and a run without the CBF may go past them",
    )
    retarget_sign: list[float] = Field(
        default_factory=lambda: [1.0] * 8,
        min_length=8,
        max_length=8,
        description="±1 per imitation joint: the robot's joint sign for a positive human angle θ_i",
    )
    capsules: dict[str, CapsuleSpec]
    self_pairs: list[tuple[str, str]] = Field(default_factory=lambda: list(DEFAULT_SELF_PAIRS))
    static_capsules: dict[str, CapsuleSpec] = Field(
        default_factory=dict,
        description="name -> capsule on a link no imitation joint moves (the pelvis under a moving waist): "
        "fixed in the world while the robot stands; kept apart from the robot capsules of static_pairs "
        "by hard CBF rows",
    )
    static_pairs: list[tuple[str, str]] = Field(
        default_factory=list, description="(robot capsule, static capsule) pairs the CBF keeps apart"
    )

    @field_validator("imitation_joints")
    @classmethod
    def _check_joints(cls, joints: list[str]) -> list[str]:
        if len(joints) != 8:
            raise ValueError(f"imitation_joints must list exactly 8 joints, got {len(joints)}")
        if any(not j for j in joints):
            raise ValueError("imitation_joints contains an empty name")
        dup = sorted({j for j in joints if joints.count(j) > 1})
        if dup:
            raise ValueError(f"imitation_joints repeats {dup}")
        if set(joints) == set(G1_IMITATION_JOINTS) and tuple(joints) != G1_IMITATION_JOINTS:
            raise ValueError(
                "imitation_joints has the G1 joints in the wrong order; the paper's order is "
                f"{list(G1_IMITATION_JOINTS)}"
            )
        return joints

    @field_validator("home")
    @classmethod
    def _check_home(cls, home: dict[str, float]) -> dict[str, float]:
        for joint, value in home.items():
            _finite(value, f"home[{joint!r}]")
        return home

    @field_validator("limits")
    @classmethod
    def _check_limits(cls, limits: dict[str, tuple[float, float]]) -> dict[str, tuple[float, float]]:
        for joint, (lo, hi) in limits.items():
            _finite(lo, f"limits[{joint!r}] min")
            _finite(hi, f"limits[{joint!r}] max")
            if not lo < hi:
                raise ValueError(f"limits[{joint!r}] must satisfy min < max, got ({lo}, {hi})")
        return limits

    @field_validator("capsules")
    @classmethod
    def _check_capsules(cls, capsules: dict[str, CapsuleSpec]) -> dict[str, CapsuleSpec]:
        missing = [n for n in CAPSULE_NAMES if n not in capsules]
        unknown = sorted(n for n in capsules if n not in CAPSULE_NAMES)
        if missing or unknown:
            raise ValueError(
                f"capsules must be exactly {list(CAPSULE_NAMES)}; missing {missing}, unknown {unknown}"
            )
        return capsules

    @field_validator("self_pairs")
    @classmethod
    def _check_pairs(cls, pairs: list[tuple[str, str]]) -> list[tuple[str, str]]:
        seen: set[frozenset[str]] = set()
        for a, b in pairs:
            for n in (a, b):
                if n not in CAPSULE_NAMES:
                    raise ValueError(
                        f"self_pairs entry ({a!r}, {b!r}) names unknown capsule {n!r}; "
                        f"known: {list(CAPSULE_NAMES)}"
                    )
            if a == b:
                raise ValueError(f"self_pairs entry ({a!r}, {b!r}) pairs a capsule with itself")
            key = frozenset((a, b))
            if key in seen:
                raise ValueError(f"self_pairs lists ({a!r}, {b!r}) twice")
            seen.add(key)
        return pairs

    @model_validator(mode="after")
    def _check_static(self) -> RobotSpec:
        clash = sorted(set(self.static_capsules) & set(CAPSULE_NAMES))
        if clash:
            raise ValueError(f"static_capsules may not reuse the robot capsule names {clash}")
        seen: set[tuple[str, str]] = set()
        for robot, static in self.static_pairs:
            if robot not in CAPSULE_NAMES or static not in self.static_capsules:
                raise ValueError(
                    f"static_pairs entry ({robot!r}, {static!r}) must name a robot capsule of {list(CAPSULE_NAMES)} "
                    f"then a static capsule of {sorted(self.static_capsules)}"
                )
            if (robot, static) in seen:
                raise ValueError(f"static_pairs lists ({robot!r}, {static!r}) twice")
            seen.add((robot, static))
        return self

    @model_validator(mode="after")
    def _check_cross_fields(self) -> RobotSpec:
        extra = sorted(set(self.limits) - set(self.imitation_joints))
        if extra:
            raise ValueError(f"limits given for joints that are not imitation joints: {extra}")
        for joint, limit in self.joint_velocity_limits.items():
            if joint not in self.imitation_joints:
                raise ValueError(f"joint_velocity_limits given for {joint!r}, which is not an imitation joint")
            if not (math.isfinite(limit) and limit > 0):
                raise ValueError(f"joint_velocity_limits[{joint!r}] must be finite and > 0, got {limit}")
        for joint, (lo, hi) in self.joint_barriers.items():
            if joint not in self.imitation_joints:
                raise ValueError(f"joint_barriers given for {joint!r}, which is not an imitation joint")
            h = self.home.get(joint, 0.0)
            if not ((lo is None or (math.isfinite(lo) and lo < h)) and (hi is None or (math.isfinite(hi) and h < hi))):
                raise ValueError(f"joint_barriers[{joint!r}] = ({lo}, {hi}) must be finite and leave home {h} strictly inside")
        for joint, (lo, hi) in self.limits.items():
            h = self.home.get(joint, 0.0)
            if not lo <= h <= hi:
                raise ValueError(f"home[{joint!r}] = {h} lies outside limits [{lo}, {hi}]")
        return self

    # ------------------------------------------------------------------ helpers
    def velocity_limits(self) -> list[float]:
        """The velocity limit of each imitation joint (rad/s, imitation_joints order; inf: unlisted)."""
        return [self.joint_velocity_limits.get(j, math.inf) for j in self.imitation_joints]

    def check_velocity_bounds(self, u_max: list[float], u_min: list[float] | None = None) -> None:
        """Raise ValueError unless |u_min| and u_max lie within :meth:`velocity_limits` on every joint."""
        bounds = [max(hi, -lo) for hi, lo in zip(u_max, u_min or [-v for v in u_max], strict=True)]
        over = [f"{j} {b} > {lim}" for j, b, lim in zip(self.imitation_joints, bounds, self.velocity_limits(), strict=True)
                if b > lim]
        if over:
            raise ValueError(f"safety velocity bounds exceed robot {self.name}'s joint_velocity_limits (rad/s): {', '.join(over)}")

    @property
    def model_path(self) -> Path:
        """``model`` as a :class:`~pathlib.Path` (absolute once loaded by :func:`load_robot_spec`)."""
        return Path(self.model)

    def with_model(self, model: str | Path) -> RobotSpec:
        """A copy of this spec driving another model file (e.g. the real G1 MJCF in tests)."""
        return self.model_copy(update={"model": str(model)})

    def within(self, ranges: dict[str, tuple[float, float]]) -> RobotSpec:
        """A copy of this spec whose ``limits`` are also within ``ranges`` (joint → (min, max) rad): each
        joint's range the intersection of both (a joint ``limits`` does not list: ``ranges``' own; the
        model's range still bounds it, :class:`~services.safety.kinematics.RobotKinematics`)."""
        limits = dict(self.limits)
        for joint, (lo, hi) in ranges.items():
            own = limits.get(joint, (-math.inf, math.inf))
            limits[joint] = (max(own[0], lo), min(own[1], hi))
        return self.model_copy(update={"limits": limits})


def default_robot_spec_path() -> Path:
    """The shipped G1 robot spec, ``config/robots/g1.yaml`` of this checkout/package."""
    return Path(__file__).resolve().parent.parent / "config" / "robots" / "g1.yaml"


def load_robot_spec(path: str | Path) -> RobotSpec:
    """Read and validate a robot spec YAML; ``model`` is resolved against the file's folder.

    Raises:
        RobotSpecError: the file is missing, is not valid YAML, is not a mapping, or fails
            validation (the message names the file and every offending field).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise RobotSpecError(f"cannot read robot spec {path}: {exc}") from exc
    return _parse_robot_spec(path, text)


@functools.lru_cache(maxsize=16)
def _parse_robot_spec(path: Path, text: str) -> RobotSpec:
    """:func:`load_robot_spec` of a file's ``text`` (cached on path and content: a YAML parse costs
    ≈ 50 ms of pure Python, paid again at every pipeline swap, on a thread that competes with the
    control loop for the GIL; a RobotSpec is frozen, so the cached one can be shared)."""
    try:
        raw: Any = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise RobotSpecError(f"robot spec {path} is not valid YAML: {exc}") from exc
    if not isinstance(raw, dict):
        raise RobotSpecError(f"robot spec {path} must be a mapping, got {type(raw).__name__}")
    model = raw.get("model")
    if isinstance(model, str) and model and not Path(model).expanduser().is_absolute():
        raw["model"] = str((path.resolve().parent / model).resolve())
    elif isinstance(model, str) and model:
        raw["model"] = str(Path(model).expanduser())
    try:
        return RobotSpec.model_validate(raw)
    except ValidationError as exc:
        raise RobotSpecError(f"invalid robot spec {path}:\n{exc}") from exc


def configured_robot_spec(conf: StackConfig) -> RobotSpec:
    """The robot description named by ``robot.spec``, with ``robot.model`` overriding its model.

    Driving a real G1 in its ``arm_sdk`` mode (``executor.backend: g1``, ``executor.g1.mode:
    arm_sdk``), the waist's range is also ``executor.g1.arm_sdk_waist_range`` (leaning over the
    running balance controller tips the robot): here, so that every service of the stack reads the
    same range — the safety layer plans and retargets within the range the executor drives, instead
    of up to 0.3 rad beyond it unnoticed (the executor clipping what the barriers were computed for)."""
    spec = load_robot_spec(resolve_config_path(conf.robot.spec, CONFIG_DIR))
    if conf.robot.model:
        spec = spec.with_model(resolve_config_path(conf.robot.model, CONFIG_DIR))
    g1 = conf.executor.g1
    if conf.executor.backend is ExecutorBackend.G1 and g1.mode is G1Mode.ARM_SDK:
        spec = spec.within(g1.arm_sdk_waist_range)
    return spec
