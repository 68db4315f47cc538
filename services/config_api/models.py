"""The config API's HTTP contract: request and response models.

Request fields use the names of the issue (``gamma``, ``phi``, ``k``, ``w``, ``u_min``, ``u_max``,
``dt``; ``S``, ``b``, ``q_home``, ``mirror``) and map onto configuration fields explicitly
(:data:`SAFETY_FIELDS`, :data:`RETARGET_FIELDS`). In a PATCH body every field is optional: an
absent field stays as it is; ``null`` is refused except where it means "the default" (``u_min``:
−u_max, ``q_home``: the robot's home pose, a robot capsule radius: the robot description's).
Bounds come from :mod:`shared.config` where it has them, so the API and the services agree.
"""

from __future__ import annotations

import math
from datetime import datetime
from typing import Annotated, Any, Literal

import annotated_types
from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, StrictBool, Strict

from services.config_api.store import HistoryEntry
from shared.bus import Received
from shared.config import (
    N_JOINTS,
    CapsuleName,
    CapsuleRadius,
    GeometryName,
    HumanConfig,
    IntrusionResponse,
    PairGroup,
    RetargetMethod,
    RetargetingConfig,
    SafetyConfig,
    StackConfig,
    TargetPath,
)
from shared.messages import HumanState, SafetyMode, SafetyStatus
from shared.names import CAPSULE_NAMES, IMITATION_JOINT_NAMES


def _like(section: type[BaseModel], name: str) -> Any:
    """The type and bounds of the number field ``section.name`` of the configuration, strict."""
    info = section.model_fields[name]
    return Annotated[info.annotation, Strict(), *info.metadata]


def _whole_number(value: Any) -> Any:
    """A JSON number with no fraction is an integer (JSON Schema): 2.0 → 2; strings and booleans stay
    refused by the strict int that follows."""
    return int(value) if isinstance(value, float) and value.is_integer() else value


def _distinct(groups: list[PairGroup]) -> list[PairGroup]:
    """A list that names each item once (JSON Schema ``uniqueItems``, as the configuration requires)."""
    if len(set(groups)) != len(groups):
        raise ValueError("lists a group twice")
    return groups


def _vector(ge: float | None = None, le: float | None = None, gt: float | None = None, lt: float | None = None) -> Any:
    """One bounded float per imitation joint (shared.names.IMITATION_JOINT_NAMES order), strict."""
    item = Annotated[float, Strict(), Field(ge=ge, le=le, gt=gt, lt=lt)]
    return Annotated[list[item], Field(min_length=N_JOINTS, max_length=N_JOINTS)]


# Numbers and booleans are strict: JSON true is not 1.0 and "2" is not 2.0 (lax pydantic would
# accept both). Request field types that carry the configuration's own bounds (shared.config is
# their one source):
_Gamma, _Phi, _Gain = (_like(SafetyConfig, name) for name in ("gamma", "phi", "gain"))
_TorsoR, _UpperArmR, _ForearmR, _ThighR = (
    _like(HumanConfig, f"{part}_radius") for part in ("torso", "upper_arm", "forearm", "thigh")
)

#: Control period bounds (s): the fastest control rate the configuration allows, and 10 Hz.
DT_MIN = 1.0 / next(c.le for c in SafetyConfig.model_fields["rate_hz"].metadata if isinstance(c, annotated_types.Le))
DT_MAX = 0.1

#: PATCH /api/config/safety field → configuration field (dotted path).
SAFETY_FIELDS: dict[str, str] = {
    "gamma": "safety.gamma",
    "phi": "safety.phi",
    "k": "safety.gain",
    "w": "safety.weights",
    "u_min": "safety.u_min",
    "u_max": "safety.u_max",
    "accel_max": "safety.accel_max",
    "self_margin": "safety.self_margin",
    "human_margin": "safety.human_margin",
    "human_predict_s": "safety.human_predict_s",
    "human_standoff_m": "safety.human_standoff_m",
    "human_speed_mps": "safety.human_speed_mps",
    "dt": "safety.rate_hz",  # dt = 1 / rate_hz
    "enabled_pair_groups": "safety.enabled_pair_groups",
    "capsule_radii.robot": "safety.capsule_radii",
    "capsule_radii.human.torso": "human.torso_radius",
    "capsule_radii.human.upper_arm": "human.upper_arm_radius",
    "capsule_radii.human.forearm": "human.forearm_radius",
    "capsule_radii.human.thigh": "human.thigh_radius",
    "human_velocity_term": "safety.human_velocity_term",
    "geometry": "safety.geometry",
    "sphere_k": "safety.sphere_k",
    "on_intrusion": "safety.on_intrusion",
    "intrusion_backout_mps": "safety.intrusion_backout_mps",
    "feedforward": "safety.feedforward",
    "target_path": "safety.target_path",
}
#: PATCH /api/config/retarget field → configuration field (dotted path).
RETARGET_FIELDS: dict[str, str] = {
    "S": "retargeting.scale",
    "b": "retargeting.offset",
    "q_home": "retargeting.q_home",
    "theta_home": "retargeting.theta_home",
    "mirror": "retargeting.mirror",
    "method": "retargeting.method",
}
#: Safety request fields whose value goes into the configuration unchanged.
_DIRECT_SAFETY = {"gamma", "phi", "k", "w", "u_min", "u_max", "accel_max", "self_margin", "human_margin", "human_predict_s",
                  "human_standoff_m", "human_speed_mps", "human_velocity_term", "feedforward", "intrusion_backout_mps",
                  "sphere_k"}
#: Safety request fields that are a choice (an enum): the configuration takes the choice's value.
_CHOICE_SAFETY = {"geometry", "on_intrusion", "target_path"}
#: Configuration field → request field, to name the request's field in errors found on the whole config.
REQUEST_FIELD: dict[str, str] = {path: name for name, path in (SAFETY_FIELDS | RETARGET_FIELDS).items()}


def _drop_null_defaults(schema: dict[str, Any]) -> None:
    """Absent means unchanged: do not advertise ``default: null`` on non-nullable fields."""
    for prop in schema.get("properties", {}).values():
        if "default" in prop and prop["default"] is None:
            del prop["default"]


class _Patch(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, json_schema_extra=_drop_null_defaults)


class _View(BaseModel):
    model_config = ConfigDict(extra="forbid")


# --------------------------------------------------------------------------------------------
# requests


class HumanRadiiPatch(_Patch):
    """Radii (m) of the person's capsules (perception sizes them: configuration section ``human``)."""

    torso: _TorsoR = None
    upper_arm: _UpperArmR = None
    forearm: _ForearmR = None
    thigh: _ThighR = None


class CapsuleRadiiPatch(_Patch):
    """Capsule radii: robot overrides by capsule name (null: back to the robot description's) and the person's."""

    robot: dict[CapsuleName, Annotated[CapsuleRadius, Strict()] | None] = None  # type: ignore[valid-type]
    human: HumanRadiiPatch = None


class SafetyPatch(_Patch):
    """A change of the CBF-QP parameters (paper eqs. 3–9); absent fields stay as they are."""

    gamma: _Gamma = Field(None, description="class-K gain γ (1/s)")
    phi: _Phi = Field(None, description="barrier margin φ (m)")
    k: _Gain = Field(None, description="K of u_ref = K (q_nom − q_cbf) (1/s)")
    w: _vector(gt=0, le=1000) = Field(None, description="diagonal of the QP weight W, per joint")
    u_min: _vector(ge=-50, lt=0) | None = Field(None, description="lower velocity bound per joint (rad/s, < 0); null: −u_max")
    u_max: _vector(gt=0, le=50) = Field(None, description="upper velocity bound per joint (rad/s, > 0)")
    accel_max: _vector(gt=0, le=10000) | None = Field(
        None, description="|u − u_prev|/Δt bound per joint (rad/s², > 0): what the motors can follow; null: none"
    )
    self_margin: _like(SafetyConfig, "self_margin") = Field(
        None, description="how far beyond φ the self-collision rows aim (m): their linearisation's drift along a curved boundary"
    )
    human_margin: _like(SafetyConfig, "human_margin") = Field(
        None, description="how much thicker every person capsule is in the CBF rows (m): the sensor's position uncertainty"
    )
    human_predict_s: _like(SafetyConfig, "human_predict_s") = Field(
        None, description="every person capsule swept ahead along its measured velocity this far (s): the delay from camera to "
        "command the position has; 0: as measured (the paper)"
    )
    human_standoff_m: _like(SafetyConfig, "human_standoff_m") = Field(
        None, description="the robot closes on no person capsule nearer than this by its own motion (m, beyond φ and the "
        "person margin); never a retreat; 0.1: a person at 1.6 m/s over the camera's 60 ms; 0: none (the paper)"
    )
    human_speed_mps: _like(SafetyConfig, "human_speed_mps") = Field(
        None, description="speed and separation: near a person no joint is asked for a speed it could not brake from "
        "before a person approaching at this speed (m/s) arrives; 1.6: ISO/TS 15066's walking speed; 0: off (the paper)"
    )
    dt: Annotated[float, Strict(), Field(ge=DT_MIN, le=DT_MAX)] = Field(None, description="control period Δt (s) = 1 / control rate")
    enabled_pair_groups: Annotated[list[PairGroup], AfterValidator(_distinct)] = Field(
        None, description="pair groups whose CBF rows are enforced, each once", json_schema_extra={"uniqueItems": True}
    )
    capsule_radii: CapsuleRadiiPatch = None
    human_velocity_term: StrictBool = Field(None, description="use the person's measured capsule velocities as a known ∂h/∂t")
    geometry: GeometryName = Field(None, description="collision geometry of the CBF rows: capsule | spheres | box (paper Table I)")
    on_intrusion: IntrusionResponse = Field(
        None, description="while a person is inside a robot capsule's margin: stop (protective stop, no retreat) | retreat"
        " | stop_on_give_way (also stop whenever a person moves in faster than the robot can retreat: it never dodges)"
    )
    intrusion_backout_mps: _like(SafetyConfig, "intrusion_backout_mps") = Field(
        None, description="during the intrusion stop, a robot capsule a still person is inside backs out of it at up to "
        "this speed (m/s); 0: it stands still until the person leaves"
    )
    sphere_k: Annotated[_like(SafetyConfig, "sphere_k"), BeforeValidator(_whole_number)] = Field(
        None, description="spheres: levels of subsampling k"
    )
    feedforward: StrictBool = Field(
        None, description="u_ref = q̇_nom + K (q_nom − q_cbf), the target's own velocity fed forward; false: the paper's eq. 7"
    )
    target_path: TargetPath = Field(
        None, description="q_nom between camera frames: jump (to each new state, then extrapolated by its rate) | continuous "
        "(no jump: from where it was to the newest state one frame ahead; for clean skeletons, it follows a camera's jitter)"
    )

    def changes(self, current: StackConfig) -> dict[str, Any]:
        """The configuration fields this patch sets on ``current`` (dotted path → new value)."""
        given = self.model_fields_set
        values = {SAFETY_FIELDS[name]: getattr(self, name) for name in given & _DIRECT_SAFETY}
        if "dt" in given:
            values[SAFETY_FIELDS["dt"]] = 1.0 / self.dt
        values |= {SAFETY_FIELDS[name]: getattr(self, name).value for name in given & _CHOICE_SAFETY}
        if "enabled_pair_groups" in given:
            values[SAFETY_FIELDS["enabled_pair_groups"]] = [g.value for g in PairGroup if g in self.enabled_pair_groups]
        radii = self.capsule_radii
        if "capsule_radii" in given and "robot" in radii.model_fields_set:
            merged = {**current.safety.capsule_radii, **radii.robot}
            values[SAFETY_FIELDS["capsule_radii.robot"]] = {k: v for k, v in merged.items() if v is not None}
        if "capsule_radii" in given and "human" in radii.model_fields_set:
            for name in radii.human.model_fields_set:
                values[SAFETY_FIELDS[f"capsule_radii.human.{name}"]] = getattr(radii.human, name)
        return values


class RetargetPatch(_Patch):
    """A change of the retargeting q_nom = clip(q_home + S ⊙ (θ − θ_home) + b, q_min, q_max) (paper eq. 2)."""

    S: _vector(ge=-5, le=5) = Field(None, description="per-joint scale S")
    b: _vector(ge=-math.pi, le=math.pi) = Field(None, description="per-joint offset b (rad)")
    q_home: _vector(ge=-math.pi, le=math.pi) | None = Field(None, description="robot pose at θ_home (rad); null: the robot description's home")
    theta_home: _vector(ge=-math.pi, le=math.pi) = Field(None, description="the person's neutral pose θ_home (rad); POST /api/calibrate captures it")
    mirror: StrictBool = Field(None, description="robot facing the person: left and right swapped, roll signs flipped")
    method: RetargetMethod = Field(
        None, description="linear: eq. 2 on every joint; directions: the arms point where the person's do (eq. 2 for the waist)"
    )

    def changes(self) -> dict[str, Any]:
        """The configuration fields this patch sets (dotted path → new value)."""
        values = {RETARGET_FIELDS[name]: getattr(self, name) for name in self.model_fields_set}
        if "method" in values:
            values[RETARGET_FIELDS["method"]] = self.method.value
        return values


# --------------------------------------------------------------------------------------------
# responses


class HumanRadii(_View):
    torso: float
    upper_arm: float
    forearm: float
    thigh: float


class CapsuleRadii(_View):
    robot: dict[str, float] = Field(description="robot capsule radius overrides (m); unlisted: the robot description's")
    human: HumanRadii


class SafetyParams(_View):
    """The CBF-QP parameters under the request's names."""

    gamma: float
    phi: float
    k: float
    w: list[float]
    u_min: list[float] | None
    u_max: list[float]
    accel_max: list[float] | None
    self_margin: float
    human_margin: float
    human_predict_s: float
    human_standoff_m: float
    human_speed_mps: float
    dt: float
    enabled_pair_groups: list[PairGroup]
    capsule_radii: CapsuleRadii
    human_velocity_term: bool
    geometry: GeometryName
    sphere_k: int
    on_intrusion: IntrusionResponse
    intrusion_backout_mps: float
    feedforward: bool
    target_path: TargetPath

    @classmethod
    def from_config(cls, conf: StackConfig) -> SafetyParams:
        s, h = conf.safety, conf.human
        return cls(
            gamma=s.gamma, phi=s.phi, k=s.gain, w=s.weights, u_min=s.u_min, u_max=s.u_max, accel_max=s.accel_max,
            self_margin=s.self_margin, human_margin=s.human_margin, human_predict_s=s.human_predict_s,
            human_standoff_m=s.human_standoff_m, human_speed_mps=s.human_speed_mps, dt=1.0 / s.rate_hz,
            enabled_pair_groups=s.enabled_pair_groups,
            capsule_radii=CapsuleRadii(
                robot=s.capsule_radii,
                human=HumanRadii(torso=h.torso_radius, upper_arm=h.upper_arm_radius, forearm=h.forearm_radius, thigh=h.thigh_radius),
            ),
            human_velocity_term=s.human_velocity_term,
            geometry=s.geometry,
            sphere_k=s.sphere_k,
            on_intrusion=s.on_intrusion,
            intrusion_backout_mps=s.intrusion_backout_mps,
            feedforward=s.feedforward,
            target_path=s.target_path,
        )


class RetargetParams(_View):
    """The retargeting parameters under the request's names."""

    S: list[float]
    b: list[float]
    q_home: list[float] | None
    theta_home: list[float]
    mirror: bool
    method: RetargetMethod

    @classmethod
    def from_config(cls, conf: RetargetingConfig) -> RetargetParams:
        return cls(S=conf.scale, b=conf.offset, q_home=conf.q_home, theta_home=conf.theta_home, mirror=conf.mirror,
                   method=conf.method)


class ConfigResponse(_View):
    """The whole configuration (secrets removed) and its version."""

    version: int = Field(description="incremented by every accepted change; 0: nothing changed yet")
    updated_at: datetime | None
    safety: SafetyParams
    retarget: RetargetParams
    config: StackConfig
    joint_names: list[str] = Field(default=list(IMITATION_JOINT_NAMES), description="order of every per-joint vector")
    capsule_names: list[str] = Field(default=list(CAPSULE_NAMES), description="the robot capsules")


class ChangeResponse(_View):
    """An accepted change: persisted and published; ``applied`` once the safety service reports it."""

    version: int = Field(description="the configuration version now current")
    applied: bool = Field(description="a SafetyStatus reported config_version ≥ version within api.ack_timeout_s")
    changed: list[str] = Field(description="configuration fields that changed (dotted paths); empty: nothing to change")
    acknowledged_version: int | None = Field(description="config_version of the newest SafetyStatus; null: none seen")
    detail: str


class CalibrateResponse(ChangeResponse):
    """The captured neutral pose θ_home (rad) and the age of the human state it came from."""

    theta_home: list[float]
    human_age_s: float


class HistoryResponse(_View):
    version: int
    entries: list[HistoryEntry] = Field(description="newest first")


class StatusResponse(_View):
    """The newest SafetyStatus seen on Zenoh (fields null until one arrives) and the person's age."""

    available: bool = Field(description="a SafetyStatus has been received")
    status_age_s: float | None = Field(description="since the newest SafetyStatus arrived (s)")
    mode: SafetyMode | None
    h_min_self: float | None = Field(description="min h over self pairs (m)")
    h_min_human: float | None = Field(description="min h over robot–human pairs (m)")
    active_constraints: int | None
    total_constraints: int | None
    solve_time_ms: float | None
    step_time_ms: float | None
    deadline_misses: int | None
    human_stale: bool | None
    watchdogs: dict[str, bool] = Field(
        description="the safety service's watchdogs now: human_stale, human_source_lost, human_lost, joint_state_stale, "
        "executor_holding, resyncing (empty until a SafetyStatus arrives)"
    )
    watchdog_trips: dict[str, int] = Field(description="times each watchdog tripped since the safety service started")
    human_age_s: float | None = Field(description="since the newest HumanState arrived here (s); null: none seen")
    applied_config_version: int | None = Field(description="config_version the safety service reports applied")
    config_version: int = Field(description="the API's current configuration version")
    backend: str | None
    dropped: dict[str, int]
    relaxed_pairs: list[str] = Field(default_factory=list, description="rows that gave way (mode relaxed): robot–person pairs, or an already violated hard row")
    person_intrusion: bool | None = Field(default=None, description="a person capsule was inside a robot capsule's margin since the previous status "
                                               "(the robot stops or retreats: safety.on_intrusion)")
    backing_out: bool | None = Field(default=None, description="the stop backed a robot arm out of a person standing still "
                                     "inside its margin since the previous status (safety.intrusion_backout_mps)")
    human_lateness_ms: float | None = Field(default=None, description="the newest HumanState was published this much later "
                                            "after its camera frame than usual (ms; 0: on time)")

    @classmethod
    def build(cls, status: Received[SafetyStatus] | None, human: Received[HumanState] | None,
              config_version: int, now: float) -> StatusResponse:
        human_age = None if human is None else now - human.received
        if status is None:
            return cls(
                available=False, status_age_s=None, mode=None, h_min_self=None, h_min_human=None,
                active_constraints=None, total_constraints=None, solve_time_ms=None, step_time_ms=None,
                deadline_misses=None, human_stale=None, watchdogs={}, watchdog_trips={}, human_age_s=human_age,
                applied_config_version=None,
                config_version=config_version, backend=None, dropped={},
            )
        s = status.message
        return cls(
            available=True, status_age_s=now - status.received, mode=s.mode, h_min_self=s.min_h_self,
            h_min_human=s.min_h_human, active_constraints=s.active_constraints, total_constraints=s.total_constraints,
            solve_time_ms=s.qp_solve_time_ms, step_time_ms=s.step_time_ms, deadline_misses=s.deadline_misses,
            human_stale=s.human_stale, human_age_s=human_age, applied_config_version=s.config_version,
            watchdogs={"human_stale": s.human_stale, "human_source_lost": s.human_source_lost, "human_lost": s.human_lost,
                       "joint_state_stale": s.joint_state_stale, "executor_holding": s.executor_holding,
                       "resyncing": s.resyncing},
            watchdog_trips=s.watchdog_trips,
            config_version=config_version, backend=s.backend, dropped=s.dropped,
            relaxed_pairs=s.relaxed_pairs, person_intrusion=s.person_intrusion, backing_out=s.backing_out,
            human_lateness_ms=s.human_lateness_ms,
        )


class HealthResponse(_View):
    status: Literal["ok"] = "ok"
    config_version: int
    uptime_s: float
    services_alive: list[str] = Field(description="services whose Zenoh liveliness token is present")
    store: str = Field(description="the file accepted changes persist to")


class ErrorResponse(_View):
    detail: str
