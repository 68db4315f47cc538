"""Stack configuration: ``config/default.yaml`` → pydantic models, with environment overrides.

Load order: the YAML file (default: the shipped ``config/default.yaml``, or ``$SAFEMIMIC_CONFIG``),
then environment variables ``SAFEMIMIC__SECTION__FIELD=value`` (value parsed as YAML), then
explicit overrides. Every error is a :class:`ConfigError` naming the offending dotted field.
"""

from __future__ import annotations

import copy
import math
import os
import re
from collections.abc import Callable, Mapping
from enum import Enum
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, model_validator

from shared.errors import SafemimicError
from shared.names import CAPSULE_NAMES, IMITATION_JOINT_NAMES

ENV_PREFIX = "SAFEMIMIC__"
CONFIG_ENV = "SAFEMIMIC_CONFIG"
#: Folder of the shipped configuration files (``config/`` next to ``shared/``).
CONFIG_DIR = Path(__file__).resolve().parent.parent / "config"
DEFAULT_CONFIG_PATH = CONFIG_DIR / "default.yaml"

N_JOINTS = len(IMITATION_JOINT_NAMES)
JointVector = Annotated[list[float], Field(min_length=N_JOINTS, max_length=N_JOINTS)]
NegativeJointVector = Annotated[list[Annotated[float, Field(lt=0)]], Field(min_length=N_JOINTS, max_length=N_JOINTS)]
#: A robot capsule name (shared.names.CAPSULE_NAMES).
CapsuleName = Literal[CAPSULE_NAMES]  # type: ignore[valid-type]
CapsuleRadius = Annotated[float, Field(gt=0, le=0.5)]


class ConfigError(SafemimicError, ValueError):
    """A configuration file, override or update is invalid; the message names the field."""


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, validate_assignment=True)


class BusMode(str, Enum):
    PEER = "peer"
    CLIENT = "client"
    ROUTER = "router"


class TlsConfig(_Section):
    """Mutual TLS of a Zenoh session (architecture §11; the files come from ``safemimic certs``).

    Either ``dir`` (a folder holding ``ca.pem`` and ``IDENTITY.pem`` / ``IDENTITY.key``) or the three
    files by name. ``identity`` is the certificate's name, by default the session's own service name
    (``safety``, ``config_api``, ``router``, ...): the router's access control knows a session by
    its certificate's common name, so a service can only do what its own certificate allows.
    ``access_control`` (router only) is the JSON5 file of Zenoh's ``access_control`` block
    (default ``dir/access_control.json5``, written by ``safemimic certs stack``).
    """

    dir: str | None = Field(default=None, description="folder with ca.pem and IDENTITY.pem/.key")
    identity: str | None = Field(default=None, pattern=r"^[A-Za-z0-9_][A-Za-z0-9_.\-]{0,63}$",
                                 description="certificate name; null: the session's service name")
    ca: str | None = Field(default=None, description="the deployment CA's certificate (default dir/ca.pem)")
    certificate: str | None = Field(default=None, description="this session's certificate (default dir/IDENTITY.pem)")
    private_key: str | None = Field(default=None, description="its private key (default dir/IDENTITY.key)")
    access_control: str | None = Field(default=None, description="router: access_control JSON5 (default dir/access_control.json5)")

    @model_validator(mode="after")
    def _files_named(self) -> TlsConfig:
        if self.dir is None and None in (self.ca, self.certificate, self.private_key):
            raise ValueError("bus.tls needs dir (holding ca.pem and IDENTITY.pem/.key) or all of ca, "
                             "certificate and private_key")
        return self


#: A Zenoh locator, ``PROTOCOL/ADDRESS[?METADATA][#CONFIG]``.
_LOCATOR = re.compile(r"(?P<protocol>[a-z][a-z0-9-]*)/(?P<address>[^?#\s]+)(?:\?[^#\s]*)?(?:#\S*)?")
#: The protocols whose address is ``HOST:PORT`` (an IPv6 host in brackets).
_HOST_PORT_PROTOCOLS = frozenset({"tcp", "udp", "tls", "quic", "ws"})
_HOST_PORT = re.compile(r"(?:\[[0-9A-Za-z:.%]+\]|[^:\[\]/]+):(?P<port>[0-9]{1,5})")


def check_endpoint(endpoint: str) -> str:
    """``endpoint`` if it is a Zenoh endpoint, ``PROTOCOL/ADDRESS`` (``tcp/10.0.0.2:7447``,
    ``tls/robot.local:7447``, ``tcp/[::1]:7447``; for tcp, udp, tls, quic and ws the address is
    HOST:PORT, port 0–65535); else ValueError saying what is expected. Checked when the
    configuration loads, so that a typo is a configuration error and not Zenoh's parse error when
    the session opens."""
    locator = _LOCATOR.fullmatch(endpoint)
    host_port = None if locator is None else _HOST_PORT.fullmatch(locator["address"])
    if locator is None or (locator["protocol"] in _HOST_PORT_PROTOCOLS
                           and (host_port is None or int(host_port["port"]) > 65535)):
        raise ValueError(f"{endpoint!r} is not a Zenoh endpoint: expected PROTOCOL/HOST:PORT, e.g. "
                         "tcp/10.0.0.2:7447 or tls/robot.local:7447")
    return endpoint


Endpoint = Annotated[str, AfterValidator(check_endpoint)]


class BusConfig(_Section):
    """Zenoh session settings (architecture §1, §11).

    ``tls`` null is the open development bus (plain tcp, no authentication: anyone who reaches it
    can command the robot; a warning is logged). With ``tls`` set every session authenticates with
    its own certificate, only ``tls/`` endpoints are allowed, and the mode must be ``client`` or
    ``router``: access control is enforced at the router, so peer-to-peer sessions, which would
    bypass it, are refused (:func:`check_secure_bus`).
    """

    mode: BusMode = BusMode.PEER
    connect: list[Endpoint] = Field(default_factory=list)
    listen: list[Endpoint] = Field(default_factory=list)
    multicast_scouting: bool = True
    max_message_bytes: int = Field(default=262144, ge=1024, le=64 * 1024 * 1024)
    lease_ms: int = Field(default=500, ge=100, le=60000)
    tls: TlsConfig | None = Field(default=None, description="mutual TLS; null: the open tcp bus (development only)")

    @model_validator(mode="after")
    def _secure_shape(self) -> BusConfig:
        check_secure_bus(self, error=ValueError)
        return self


def check_secure_bus(bus: BusConfig, error: type[Exception] | None = None) -> None:
    """With ``bus.tls`` set: mode client or router and ``tls/`` endpoints only; else ``error`` (default
    :class:`ConfigError`) saying what to change."""
    if bus.tls is None:
        return
    if bus.mode == BusMode.PEER:
        raise (error or ConfigError)("bus.tls: a secure bus needs mode client (through the router, which enforces access "
                    "control) or router; peer-to-peer sessions would bypass it (use --mode client, or "
                    "--insecure for an open development bus)")
    plain = [endpoint for endpoint in (*bus.connect, *bus.listen) if not endpoint.startswith("tls/")]
    if plain:
        raise (error or ConfigError)(f"bus.tls: every endpoint must be tls/HOST:PORT, not {', '.join(plain)} "
                    "(or --insecure for an open tcp bus)")


class RobotConfig(_Section):
    """Which robot description to use (robots/*.yaml) and an optional model override."""

    spec: str = "robots/g1.yaml"
    model: str | None = None


class RetargetMethod(str, Enum):
    """How the person's pose becomes the robot's target (services.safety.assembly.make_retargeter)."""

    LINEAR = "linear"  # paper eq. 2 on every joint
    DIRECTIONS = "directions"  # eq. 2 for the waist; the arms point where the person's do (through the robot's kinematics)


class RetargetingConfig(_Section):
    """Paper eq. 2: q_nom = clip(q_home + S ⊙ (θ − θ_home) + b, q_min, q_max); ``directions``: the
    arms instead by their segments' directions (services.safety.direction_retarget)."""

    method: RetargetMethod = Field(
        default=RetargetMethod.LINEAR,
        description="linear: paper eq. 2 on every joint (the default: it keeps the paper's scenarios inside the "
        "barriers); directions: eq. 2 for the waist, the arms solved through the robot's kinematics so that its upper "
        "arms and forearms point where the person's do (S, b, θ_home, q_home then apply to the waist only): far closer "
        "imitation, but on the G1 its arms reach further toward a person (README, 'The development set')",
    )

    scale: JointVector = Field(default_factory=lambda: [1.0] * N_JOINTS)
    offset: JointVector = Field(default_factory=lambda: [0.0] * N_JOINTS)
    theta_home: JointVector = Field(default_factory=lambda: [0.0] * N_JOINTS)
    mirror: bool = False
    q_home: JointVector | None = Field(default=None, description="robot pose for θ = θ_home (rad); null: the robot description's home")


class QPBackendName(str, Enum):
    DAQP = "daqp"
    OSQP = "osqp"


class PairGroup(str, Enum):
    """Groups of monitored capsule pairs that can be switched on and off together.

    A robot–human pair is ``human``; a self pair is ``self_torso`` if it involves the torso or a
    static trunk capsule (the robot description's ``static_pairs``: the arms against the pelvis),
    else ``self_legs`` if it involves a thigh, else ``self_arms`` (arm against arm).
    """

    SELF_ARMS = "self_arms"
    SELF_TORSO = "self_torso"
    SELF_LEGS = "self_legs"
    HUMAN = "human"


class GeometryName(str, Enum):
    """Collision geometry of the CBF rows (paper §IV-B, Table I; services.safety.barriers)."""

    CAPSULE = "capsule"
    SPHERES = "spheres"
    BOX = "box"


class IntrusionResponse(str, Enum):
    """What the robot does while a person is inside a robot capsule's margin, or moves in faster than it can
    retreat (services.safety.filter): ``stop`` inside a margin; ``stop_on_give_way`` also whenever a person row
    gives way (the robot never dodges); ``retreat`` never stops for either."""

    STOP = "stop"
    RETREAT = "retreat"
    STOP_ON_GIVE_WAY = "stop_on_give_way"


class TargetPath(str, Enum):
    """How q_nom moves between camera frames (services.safety.nominal): ``jump`` to the newest state at each
    frame, then extrapolated by its rate; ``continuous`` from where it was to the newest state extrapolated one
    frame ahead, arriving when the next frame is due (no jump)."""

    JUMP = "jump"
    CONTINUOUS = "continuous"


PositiveJointVector = Annotated[list[Annotated[float, Field(gt=0)]], Field(min_length=N_JOINTS, max_length=N_JOINTS)]


class SafetyConfig(_Section):
    """CBF-QP parameters (paper eqs. 3–9; architecture §4)."""

    rate_hz: float = Field(default=500.0, gt=0, le=5000)
    status_rate_hz: float = Field(default=50.0, gt=0, le=1000)
    gamma: float = Field(default=10.0, gt=0, le=1000, description="class-K gain γ (1/s)")
    phi: float = Field(default=0.02, ge=0, le=0.5, description="barrier margin φ (m)")
    gain: float = Field(default=8.0, gt=0, le=1000, description="K of u_ref = K (q_nom − q_cbf) (1/s)")
    weights: JointVector = Field(default_factory=lambda: [1.0] * N_JOINTS)
    u_max: JointVector = Field(
        default_factory=lambda: [3.0, 3.0, 10.0, 10.0, 10.0, 10.0, 10.0, 10.0],
        description="|u| bound per joint (rad/s), within the robot description's joint_velocity_limits (the G1's "
        "published 37 rad/s): the person's own retargeted joint speeds on the development clips are p99 1–2 rad/s "
        "at the waist and 6–10 rad/s at the arms (a punch's elbow 25), so 10 follows ordinary fast arm motion "
        "(jumping jacks, punches but their peaks) unsaturated; the waist stays at 3 (it carries the upper body "
        "over the balance controller)",
    )
    accel_max: PositiveJointVector | None = Field(
        default_factory=lambda: [10.0, 10.0, 60.0, 60.0, 250.0, 60.0, 60.0, 250.0],
        description="|u − u_prev|/Δt bound per joint (rad/s²): the command changes speed no faster than the motors can "
        "follow, so the robot stays on the path the barriers were computed for. About half of each G1 motor's torque "
        "(Unitree: arms 25 N·m, waist 50 N·m) over the largest inertia its joint sees over the range (Pinocchio: "
        "shoulder 0.21, elbow 0.044 kg·m²): shoulders 60, elbows 250; the waist a quarter of 50 N·m over 1.3 kg·m² "
        "(it also takes the arms' reaction torques): 10. The bound gives way (widened step by step, reported as "
        "'accel_max') only where no u within it keeps every hard row; null: no bound (the paper)",
    )
    self_margin: float = Field(
        default=0.002, ge=0, le=0.05,
        description="the hard distance rows (self pairs, static pairs) aim this far (m) beyond φ. Rows linearised "
        "once a step drift into a curved boundary while the robot slides along it, to a depth of ≈ κ v² Δt / (2γ) "
        "(κ the boundary's curvature, v the sliding speed): 2 mm at 1 m/s along the thinnest robot capsule (r 0.05 m, "
        "κ = 20 /m) at Δt = 2 ms and γ = 10. h is still reported against φ; 0: none (the paper)",
    )
    feedforward: bool = Field(
        default=True,
        description="u_ref = q̇_nom + K (q_nom − q_cbf) with q̇_nom the retargeted θ̇ of the human state (no lag "
        "behind a ramp); false: the paper's eq. 7, u_ref = K (q_nom − q_cbf) (a lag of ≈ 1/K)",
    )
    extrapolate_max_s: float = Field(
        default=0.05, ge=0, le=0.5,
        description="between camera frames q_nom is extrapolated by its rate for one frame period (the interval of "
        "the newest two human states' stamps) but at most this long (s); 0: held as a staircase",
    )
    target_path: TargetPath = Field(
        default=TargetPath.JUMP,
        description="'jump': at each camera frame q_nom jumps to the new state, then is extrapolated by its rate, and "
        "K closes the jump in ≈ 1/K (which also smooths a noisy camera's jitter); 'continuous': q_nom moves from where "
        "it was to the newest state extrapolated one frame period ahead, arriving when the next frame is due, and that "
        "path's velocity is fed forward: ≈ 20 ms less lag on clean skeletons (motion capture), but a camera's jitter "
        "is followed within a frame (README 'Velocity feed-forward and targets between frames')",
    )
    backend: QPBackendName = QPBackendName.DAQP
    pairs: str = Field(default="default", pattern=r"^[a-z0-9_]+$")
    geometry: GeometryName = Field(default=GeometryName.CAPSULE, description="collision geometry of the CBF rows")
    sphere_k: int = Field(default=1, ge=0, le=3, description="spheres: levels of subsampling k (each halves the spacing)")
    human_velocity_term: bool = True
    human_margin: float = Field(
        default=0.02, ge=0, le=0.2,
        description="every person capsule is this much thicker in the CBF rows (m): ISO/TS 15066's Z_d, the person "
        "sensor's position uncertainty beyond what the look-ahead covers (a camera skeleton's joints are off by "
        "centimetres); h of a person row counts it",
    )
    human_lookahead_s: float = Field(
        default=0.11, ge=0, le=1,
        description="an approaching person is anticipated this far ahead (s): the delay from camera to command, as "
        "ISO/TS 15066 separation monitoring counts v_h·(T_r + T_s): camera latency 0.060 (exposure, readout, pose "
        "inference, transport) + one 30 Hz frame of hold 0.033 + the point filter's lag ≤ 0.016 (EMA τ = 0.03 s "
        "at 30 Hz; One Euro ≈ 0.009) ≈ 0.11",
    )
    human_predict_s: float = Field(
        default=0.093, ge=0, le=0.5,
        description="every fresh person capsule is replaced in the rows by the capsule that encloses it both where it "
        "was seen and where its measured velocity carries it in this time τ (s): camera latency 0.060 + one 30 Hz "
        "frame held 0.033, how old the measured position is when the robot acts on it (the point filter's lag is "
        "in human_lookahead_s). Axis moved by v·τ/2, radius + max|v|·τ/2, so a noisy velocity only makes the rows "
        "more cautious; the intrusion stop still needs the measured capsule inside. 0: as measured (the paper). "
        "docs/safety-measurements.md 'Sweeping the person ahead'",
    )
    on_intrusion: IntrusionResponse = Field(
        default=IntrusionResponse.STOP,
        description="while a person capsule is inside a robot capsule's margin (h < −1 mm on a person row): stop "
        "(the protective stop of ISO/TS 15066 speed and separation monitoring: brake to rest within the acceleration "
        "bound, never closer to any person capsule, no retreat demanded, imitation resumes once no person row is "
        "inside and the rows can be kept: a step right after a stop whose person rows give way stops too) or retreat (the CBF's own answer: every violated row demands A u ≥ −γ h, the least total violation "
        "first, then the target is rest). Measured: the robot closes 2.4–5× less distance into the true person in contact, at 11–30 % "
        "more contact steps, which are the person's: docs/safety-measurements.md 'The intrusion stop'. stop_on_give_way: the same stop "
        "also whenever the person rows cannot all be honoured (a person moving in faster than the robot can "
        "retreat): the robot never dodges; on the test variants of the recordings 93 % fewer robot-caused contact "
        "steps, but a person's arm sweeping past meets a robot that stands still (the paper's side-by-side arm raise: "
        "680 contact steps instead of 0) and with a noisy camera 166 robot-caused steps instead of 22",
    )
    intrusion_backout_mps: float = Field(
        default=0.05, ge=0, le=0.25,
        description="during the intrusion stop, while the person stands still (seen to move slower than 0.15 m/s "
        "over up to the last second, at least 0.5 s, which a camera's noise averages out; none held from memory or just appeared) inside the "
        "margins of the robot's arms only, each arm backs out of the person capsules it holds at up to this speed (m/s, along the pair's normal) until none is inside: a person who "
        "stands in an arm's margin does not freeze the robot there. 0: it stands still until they leave. docs/safety-measurements.md "
        "'Backing out from a person who stands inside'",
    )
    human_standoff_m: float = Field(
        default=0.1, ge=0, le=0.3,
        description="the robot closes on no person capsule nearer than this by its own motion (m, beyond φ and "
        "human_margin): each person row allows closing at γ (h − D) instead of γ h, none at h ≤ D (but a 0.1 mm/s "
        "creep), and never demands a retreat (ISO/TS 15066's protective separation for a person who starts to move "
        "before the camera shows it). Default 0.1: a person at 1.6 m/s over the camera's 60 ms latency; it halved the "
        "robot-caused contact steps over seven measured sets and costs imitation beside a person. 0: none (the "
        "paper). services/safety/standoff.py; docs/safety-measurements.md 'A standoff from the person'",
    )
    human_speed_mps: float = Field(
        default=1.6, ge=0, le=5.0,
        description="speed and separation (m/s): near a person the tracking asks no joint for a speed it could not "
        "brake from (at accel_max) before a person approaching at this speed reaches the robot; only the reference "
        "u_ref is capped, in both directions (the rows and the QP's feasibility are untouched). 1.6 (the default): "
        "ISO/TS 15066's and ISO 13855's walking speed; 0: off (the paper). services/safety/separation.py; "
        "docs/safety-measurements.md 'Speed and separation'",
    )
    human_timeout_s: float = Field(default=0.5, gt=0, le=60)
    lost_human_hold_s: float = Field(
        default=2.0, gt=0, le=60,
        description="a capsule perception stops seeing is held this long (s) from its last valid one, imitation stopped",
    )
    joint_state_timeout_s: float = Field(default=0.1, gt=0, le=60)
    relax_penalty: float = Field(
        default=100.0, ge=1, le=1000,
        description="when the rows are infeasible: the cost of an already-violated hard row's slack (a self pair or "
        "joint barrier, which must not happen) relative to a person row's (1) in the least-violation stage",
    )
    u_min: NegativeJointVector | None = Field(default=None, description="lower velocity bound per joint (rad/s); null: −u_max")
    enabled_pair_groups: list[PairGroup] = Field(
        default_factory=lambda: list(PairGroup), description="pair groups whose CBF rows are enforced"
    )
    capsule_radii: dict[CapsuleName, CapsuleRadius] = Field(
        default_factory=dict, description="robot capsule radius overrides (m); unlisted: the robot description's"
    )

    @model_validator(mode="after")
    def _unique_pair_groups(self) -> SafetyConfig:
        if len(set(self.enabled_pair_groups)) != len(self.enabled_pair_groups):
            raise ValueError("enabled_pair_groups lists a group twice")
        return self

    @model_validator(mode="after")
    def _positive_vectors(self) -> SafetyConfig:
        if min(self.weights) <= 0:
            raise ValueError("weights must all be > 0 (W ≻ 0)")
        if min(self.u_max) <= 0:
            raise ValueError("u_max must all be > 0")
        return self


class ExecutorBackend(str, Enum):
    MUJOCO = "mujoco"
    G1 = "g1"


class G1Mode(str, Enum):
    """How the G1 executor commands the robot: ``rt/arm_sdk`` (upper body blended over the running
    balance controller) or ``rt/lowcmd`` (every motor; the balance controller must be released)."""

    ARM_SDK = "arm_sdk"
    LOWCMD = "lowcmd"


class G1ArmSdkJoints(str, Enum):
    """Which upper-body motors an ``rt/arm_sdk`` frame commands: all 17 (the default, as Unitree's
    arm example does: the others than the imitation joints held at the pose measured when the
    ramp-in began) or the imitation joints only (the others left unset, for firmware that keeps the
    balance controller's values there at full blend weight: seen on a gantry first)."""

    IMITATION = "imitation"
    UPPER_BODY = "upper_body"


class G1Waist(str, Enum):
    """Whether waist roll/pitch can move: from ``LowState_.mode_machine`` (auto) or as configured."""

    AUTO = "auto"
    LOCKED = "locked"
    UNLOCKED = "unlocked"


class G1LockedWaistPolicy(str, Enum):
    """What to do when the waist is locked but imitated: refuse to start, or imitate the arms only."""

    REFUSE = "refuse"
    ARMS_ONLY = "arms_only"


#: Upper bounds of the G1 executor's per-joint settings, so that no configuration (a typo, a copied
#: value from another robot) commands the real robot beyond what its motors are meant for: a stiffness
#: of 500 N·m/rad is over twice the stiffest of Unitree's own tables (the knees' 200 in its walking
#: policies), a damping of 20 N·m·s/rad ten times its arms', and 37 rad/s is the motors' rated speed
#: (``joint_velocity_limits`` of config/robots/g1.yaml), which also bounds the jump the last check of
#: a frame accepts (derived from ``max_speed``).
G1_MAX_KP, G1_MAX_KD, G1_MAX_SPEED = 500.0, 20.0, 37.0
#: The shortest hand-over ramps (s): a weight stepping 0 → 1 in a few ticks snaps the arms between
#: the balance controller's pose and ours.
G1_MIN_RAMP_S = 0.25


_PerJoint = Field(min_length=N_JOINTS, max_length=N_JOINTS)
G1Stiffness = Annotated[list[Annotated[float, Field(gt=0, le=G1_MAX_KP)]], _PerJoint]
G1Damping = Annotated[list[Annotated[float, Field(ge=0, le=G1_MAX_KD)]], _PerJoint]
G1Speed = Annotated[list[Annotated[float, Field(gt=0, le=G1_MAX_SPEED)]], _PerJoint]


class G1Config(_Section):
    """The Unitree G1 hardware executor (``--backend g1``, architecture §11). Vectors are per imitation
    joint, in the robot description's order."""

    mode: G1Mode = G1Mode.ARM_SDK
    arm_sdk_joints: G1ArmSdkJoints = Field(
        default=G1ArmSdkJoints.UPPER_BODY,
        description="arm_sdk: upper_body (all 17 upper-body motors, as Unitree's arm example; the others than the "
        "imitation joints held at the pose measured when the ramp began) | imitation (only the imitation joints: "
        "whether the firmware keeps the balance controller's values for the unset slots at full blend weight, or "
        "lets them go limp, must be seen on a gantry first)",
    )
    network_interface: str | None = Field(
        default=None, pattern=r"^[A-Za-z0-9_.:\-]{1,64}$",
        description="interface facing the robot (e.g. eth0); null: CycloneDDS's choice or $CYCLONEDDS_URI",
    )
    domain_id: int = Field(default=0, ge=0, le=232, description="DDS domain (the robot uses 0)")
    dry_run: bool = Field(default=False, description="read rt/lowstate, build and check every frame, print them, send nothing")
    waist: G1Waist = G1Waist.AUTO
    on_locked_waist: G1LockedWaistPolicy = G1LockedWaistPolicy.REFUSE
    ramp_in_s: float = Field(default=3.0, ge=G1_MIN_RAMP_S, le=60, description="blend weight 0 → 1 from the measured pose (s)")
    ramp_out_s: float = Field(default=2.0, ge=G1_MIN_RAMP_S, le=60, description="blend weight → 0 on stop, timeout or fault (s)")
    command_timeout_s: float = Field(default=0.3, gt=0, le=10, description="no new target for this long: ramp out (s)")
    state_timeout_s: float = Field(default=0.1, gt=0, le=10, description="no rt/lowstate for this long: ramp out (s)")
    state_wait_s: float = Field(default=5.0, gt=0, le=120, description="start fails without rt/lowstate within this time (s)")
    kp: G1Stiffness = Field(default_factory=lambda: [60.0] * N_JOINTS, description="servo stiffness (N·m/rad, ≤ 500)")
    kd: G1Damping = Field(default_factory=lambda: [1.5] * N_JOINTS, description="servo damping (N·m·s/rad, ≤ 20)")
    stop_damping: float = Field(
        default=2.0, ge=1, le=5,
        description="kd of the imitation joints × this while the safety service commands a protective stop "
        "(JointCommand.protective_stop): the arms brake to rest with less overshoot. At kp 60 / kd 1.5 the shoulders' "
        "damping ratio is ≈ 0.2 (our model's inertia at home), 0.43 at ×2; check on the robot before raising it",
    )
    max_speed: G1Speed = Field(
        default_factory=lambda: [3.0, 3.0, 6.0, 6.0, 6.0, 6.0, 6.0, 6.0],
        description="the sent target moves at most this fast (rad/s, ≤ the motors' 37)",
    )
    position_margin: float = Field(default=0.05, ge=0, le=0.3, description="targets stay this far inside the joint range (rad)")
    torque_fraction: float = Field(
        default=0.8, gt=0, le=1, description="targets stay within torque_fraction · limit / kp of the measured angle"
    )
    fault_speed: float = Field(default=10.0, gt=0, le=50, description="a measured joint faster than this latches a fault (rad/s)")
    dry_run_print_s: float = Field(default=0.5, gt=0, le=60, description="dry run: one frame printed this often (s)")
    arm_sdk_waist_range: dict[str, tuple[float, float]] = Field(
        default_factory=lambda: {"waist_roll_joint": (-0.1, 0.1), "waist_pitch_joint": (-0.15, 0.05)},
        description="arm_sdk mode only: waist joint -> (min, max) (rad) the imitated waist targets are clipped to. "
        "Leaning the torso over the running balance controller (worst: forward, with the arms raised forward) makes "
        "the G1 lean forward and lose balance (unitree_sdk2_python issues #146, #173; a small backward pitch "
        "helped in #173), so forward pitch (G1 +) is limited to 0.05, backward to 0.15, roll to ±0.1; {} : the "
        "hardware range. With executor.backend g1 every service reads it into the robot description, so the safety "
        "layer plans with it (shared.robot_spec.configured_robot_spec)",
    )

    @model_validator(mode="after")
    def _check_waist_range(self) -> G1Config:
        for joint, (lo, hi) in self.arm_sdk_waist_range.items():
            if joint not in ("waist_roll_joint", "waist_pitch_joint"):
                raise ValueError(f"arm_sdk_waist_range: {joint!r} is not waist_roll_joint or waist_pitch_joint")
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= 0.0 <= hi and lo < hi):
                raise ValueError(f"arm_sdk_waist_range[{joint!r}] = ({lo}, {hi}) must be finite with min ≤ 0 ≤ max, min < max")
        return self


class ExecutorConfig(_Section):
    """Simulated (or hardware) executor: joint PD gains and rates."""

    rate_hz: float = Field(default=500.0, gt=0, le=10000)
    state_rate_hz: float = Field(default=200.0, gt=0, le=2000)
    kp: float = Field(default=150.0, gt=0)
    kd: float = Field(default=5.0, ge=0)
    command_timeout_s: float = Field(default=0.2, gt=0)
    viewer: bool = False
    joint_gains: dict[str, tuple[float, float]] = Field(
        default_factory=lambda: {"waist_roll_joint": (300.0, 30.0), "waist_pitch_joint": (300.0, 30.0),
                                 "waist_yaw_joint": (500.0, 30.0)},
        description="per-joint (kp, kd) overriding kp/kd or hold_kp/hold_kd; the waist carries the whole "
        "upper body (at home 0.90 kg·m² in roll, 0.56 in pitch, 0.38 in yaw), so kd = 5 (imitated roll, pitch) or "
        "hold_kd = 10 (held yaw: damping ratio 0.36) would leave it ringing; these damp every waist servo about "
        "critically (ratio 0.91–1.16)",
    )
    hold_kp: float = Field(default=500.0, gt=0, description="servo stiffness of the joints held at home (N·m/rad)")
    hold_kd: float = Field(default=10.0, ge=0, description="servo damping of the joints held at home (N·m·s/rad)")
    stop_damping: float = Field(
        default=2.0, ge=1, le=5,
        description="kd of the imitation joints × this while the safety service commands a protective stop "
        "(JointCommand.protective_stop; 1: off). A stop brakes to rest, where the servo's overshoot carries the arm "
        "on into whatever stopped it: ×2 brings the shoulders (kp 150, kd 5: damping ratio 0.45–0.48 at home) to "
        "about critical (0.90–0.95), the fastest approach to rest without overshoot",
    )
    gravity_compensation: bool = Field(
        default=True, description="simulation: the servos add the links' gravity torque (within their torque limits)"
    )
    torque_feedforward: bool = Field(
        default=True,
        description="simulation: the servos add the inverse dynamics of the commanded motion, M(q) q̈_ref + c(q, q̇) "
        "(the command's acceleration through the joint-space inertia, and the Coriolis/centrifugal torques; gravity "
        "is gravity_compensation's) on every servo (the joints held at home take the reaction), plus the joints' "
        "Coulomb friction in the direction of the commanded velocity, so a PD servo follows an acceleration-bounded "
        "command instead of trailing it by M q̈/kp (and a slow one by friction/kp); false: position + velocity "
        "feed-forward only",
    )
    stats_interval_s: float = Field(default=5.0, gt=0, le=3600, description="one-line summary this often (s)")
    backend: ExecutorBackend = Field(default=ExecutorBackend.MUJOCO, description="mujoco (simulation) | g1 (the real robot)")
    g1: G1Config = Field(default_factory=G1Config)

    @model_validator(mode="after")
    def _positive_joint_gains(self) -> ExecutorConfig:
        for joint, (kp, kd) in self.joint_gains.items():
            if not (kp > 0 and kd >= 0):
                raise ValueError(f"joint_gains[{joint!r}] must have kp > 0 and kd >= 0, got ({kp}, {kd})")
        return self


class ApiConfig(_Section):
    """Config API server."""

    host: str = "127.0.0.1"
    port: int = Field(default=8080, ge=0, le=65535)
    store: str | None = None
    token: str | None = Field(default=None, min_length=16, max_length=256, description="bearer token for writes")
    ack_timeout_s: float = Field(default=2.0, gt=0, le=60, description="wait this long for the safety service to apply a change")
    history_length: int = Field(default=100, ge=1, le=10000, description="accepted changes kept in the store")
    max_body_bytes: int = Field(default=65536, ge=1024, le=16 * 1024 * 1024)
    cors_origins: list[str] = Field(default_factory=list, description="origins allowed by CORS; empty: no CORS")
    calibrate_max_age_s: float = Field(default=0.5, gt=0, le=60, description="newest human state must be this fresh")
    stream_rate_hz: float = Field(default=20.0, gt=0, le=100, description="status events per second on the live stream")


_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
#: ``auto``, a named placement, ``recorded`` (as recorded) or ``x,y,yaw`` (m, m, rad).
PLACEMENT_PATTERN = rf"^(?:auto|side-by-side|facing|recorded|{_NUMBER},{_NUMBER},{_NUMBER})$"


class SkeletonSourceName(str, Enum):
    REPLAY = "replay"
    SCENARIO = "scenario"
    CAMERA = "camera"  # OpenCV capture + BlazePose (monocular 3D pose)
    ZED = "zed"  # ZED SDK body tracking (needs pyzed)


class PoseEstimatorName(str, Enum):
    CONTINUOUS = "continuous"
    PAPER = "paper"


class PointFilterKind(str, Enum):
    """The smoothing step of the point filter: the paper's EMA, or the One Euro filter (Casiez et al. 2012)."""

    EMA = "ema"
    ONE_EURO = "one_euro"


class PointFilterConfig(_Section):
    """Per-keypoint smoothing + jump rejection (paper §II-A), in the robot frame.

    ``kind: ema``: gain per frame α = 1 − exp(−Δt/τ); the steady-state lag behind a
    constant-velocity point is Δt (1 − α)/α ≈ τ − Δt/2 seconds. ``kind: one_euro``: α = 1/(1 + τ/Δt),
    τ = 1/(2π f_c), f_c = ``min_cutoff_hz`` + ``beta``·‖v̂‖ with v̂ the point's velocity low-passed at
    ``d_cutoff_hz`` (services.perception.point_filter).
    """

    kind: PointFilterKind = Field(default=PointFilterKind.ONE_EURO, description="smoothing step: ema | one_euro")
    min_confidence: float = Field(default=0.3, ge=0, le=1, description="below: the point is missing this frame")
    ema_tau_s: float = Field(default=0.03, ge=0, le=2, description="EMA time constant τ (s); 0: no smoothing")
    min_cutoff_hz: float = Field(default=1.0, gt=0, le=100, description="One Euro: cut-off of a still point (Hz)")
    beta: float = Field(default=20.0, ge=0, le=1000, description="One Euro: cut-off growth with speed (Hz per m/s)")
    d_cutoff_hz: float = Field(default=1.0, gt=0, le=100, description="One Euro: cut-off of the velocity estimate (Hz)")
    max_speed: float = Field(default=12.0, gt=0, le=100, description="faster apparent motion is a jump: rejected (m/s)")
    reacquire_frames: int = Field(default=3, ge=1, le=100, description="consistent rejected frames that re-anchor a point")
    hold_s: float = Field(default=0.25, ge=0, le=10, description="a missing point is held this long, then invalid (s)")
    reset_gap_s: float = Field(default=1.0, gt=0, le=60, description="no frame for this long: full filter reset (s)")


class PoseAnglesConfig(_Section):
    """The 8 pose angles θ (paper §II-A): estimator and its conditioning thresholds."""

    estimator: PoseEstimatorName = PoseEstimatorName.CONTINUOUS
    paper_zone: float = Field(
        default=0.5, gt=0, le=1,
        description="continuous = paper where the upper arm points down by at least this (−u_z ≥ it)",
    )
    pitch_observability: float = Field(
        default=0.2, ge=0, le=1, description="|sagittal projection| below which pitch updates are damped"
    )
    min_segment: float = Field(default=0.05, gt=0, le=1, description="shorter segments make angles invalid (m)")
    seam: float = Field(
        default=1.25 * math.pi, gt=math.pi, le=1.5 * math.pi,
        description="continuous shoulder angles lie in [seam − 2π, seam] (rad): the wrap is behind/over the head",
    )
    branch_switch_rate: float = Field(
        default=4.0, gt=0, le=100,
        description="a shoulder angle's branch switch (a jump ≥ π/2 in one frame) is spread at this rate (rad/s)",
    )
    rate_cutoff_hz: float = Field(
        default=1.0, gt=0, le=100,
        description="θ̇ (HumanState.theta_rate): low-pass cut-off of the difference of a still angle (Hz)",
    )
    rate_beta: float = Field(
        default=10.0, ge=0, le=1000,
        description="θ̇: the cut-off grows by this much per rad/s of the angle's speed (Hz per rad/s; One Euro); "
        "0: a fixed cut-off",
    )
    rate_second_order: bool = Field(
        default=False,
        description="θ̇: the slope at the newest frame of the parabola through the last three (exact for a constant "
        "acceleration); false: the last difference (half a frame late)",
    )

    @model_validator(mode="after")
    def _observability_inside_paper_zone(self) -> PoseAnglesConfig:
        if self.pitch_observability > self.paper_zone:
            raise ValueError("pitch_observability must not exceed paper_zone (the paper zone is never damped)")
        return self


Vector3 = Annotated[list[float], Field(min_length=3, max_length=3)]


class CameraIntrinsics(_Section):
    """Pinhole intrinsics of the captured image (pixels); a null field comes from ``hfov_deg`` and the size.

    K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]; by default fx = fy = (width / 2) / tan(hfov / 2),
    cx = width / 2, cy = height / 2. ``distortion``: OpenCV coefficients (k1, k2, p1, p2[, k3, ...]);
    empty: none.
    """

    fx: float | None = Field(default=None, gt=0)
    fy: float | None = Field(default=None, gt=0)
    cx: float | None = Field(default=None, ge=0)
    cy: float | None = Field(default=None, ge=0)
    hfov_deg: float = Field(default=60.0, gt=10, lt=170, description="horizontal field of view when fx/fy are null")
    distortion: list[float] = Field(default_factory=list, max_length=14)


class CameraExtrinsics(_Section):
    """The camera's pose in the robot frame (x forward, y left, z up, floor z = 0).

    The camera body frame is x along the optical axis, y left, z up (ROS ``camera_link``; a level
    camera with roll = pitch = yaw = 0 looks along the robot's +x). p_robot = position +
    R_z(yaw) R_y(pitch) R_x(roll) p_body; positive pitch tilts the view down. OpenCV's optical
    frame (x right, y down, z forward) is p_body = (z, −x, −y).
    """

    position: Vector3 = Field(default_factory=lambda: [2.5, 0.0, 1.2], description="camera centre in the robot frame (m)")
    rpy: Vector3 = Field(default_factory=lambda: [0.0, 0.0, 3.141592653589793], description="roll, pitch, yaw (rad)")


class CameraConfig(_Section):
    """Live sources (``camera``: OpenCV + BlazePose; ``zed``: ZED SDK body tracking) and their mounting."""

    device: int | str = Field(default=0, description="camera index, or a video file / stream URL")
    width: int = Field(default=640, ge=64, le=7680, description="requested from a camera device (px)")
    height: int = Field(default=480, ge=64, le=4320, description="requested from a camera device (px)")
    fps: float = Field(default=30.0, gt=0, le=240, description="requested from a camera device")
    intrinsics: CameraIntrinsics = Field(default_factory=CameraIntrinsics)
    extrinsics: CameraExtrinsics = Field(default_factory=CameraExtrinsics)
    model_dir: str | None = Field(default=None, description="BlazePose weights; null: ~/.cache/safemimic/models")
    detection_threshold: float = Field(default=0.5, gt=0, lt=1, description="person detector score to accept")
    presence_threshold: float = Field(default=0.5, gt=0, lt=1, description="landmark model pose presence to keep a track")
    threads: int = Field(default=2, ge=1, le=64, description="inference threads")
    zed_body_format: Literal["body_18", "body_34"] = "body_34"


class PerceptionConfig(_Section):
    """Perception service (architecture §1): skeleton source → point filter → θ + human capsules."""

    source: SkeletonSourceName = SkeletonSourceName.SCENARIO
    recording: str | None = Field(default=None, description=".npz recording of the replay source (architecture §6)")
    scenario: str = Field(default="neutral", pattern=r"^[a-z0-9\-]+$")
    scenario_fps: float = Field(default=30.0, gt=0, le=1000)
    scenario_shoulder_width: float = Field(default=0.36, ge=0.15, le=0.5, description="synthetic person (m)")
    realtime: bool = Field(default=True, description="pace frames at the source rate; false: as fast as possible")
    loop: bool = False
    placement: str = Field(default="auto", pattern=PLACEMENT_PATTERN)
    side_by_side_y: float = Field(default=0.70, ge=-5, le=5, description="side-by-side: lateral offset, + = robot's left (m)")
    facing_distance: float = Field(default=0.95, ge=0, le=10, description="facing: distance in front of the robot (m)")
    wait_subscriber_s: float = Field(default=0.0, ge=0, le=600, description="wait up to this long for a subscriber")
    stats_interval_s: float = Field(default=5.0, gt=0, le=3600)
    point_filter: PointFilterConfig = Field(default_factory=PointFilterConfig)
    angles: PoseAnglesConfig = Field(default_factory=PoseAnglesConfig)
    camera: CameraConfig = Field(default_factory=CameraConfig)


class HumanConfig(_Section):
    """The 7 human capsules (paper §III-A): radii (m) around the keypoint segments."""

    torso_radius: float = Field(default=0.15, gt=0, le=0.5)
    upper_arm_radius: float = Field(default=0.06, gt=0, le=0.3)
    forearm_radius: float = Field(default=0.05, gt=0, le=0.3)
    thigh_radius: float = Field(default=0.08, gt=0, le=0.3)
    hand_extension: float = Field(default=0.10, ge=0, le=0.3, description="forearm capsule reaches past the wrist (m)")


class StackConfig(_Section):
    """The whole stack's configuration (config/default.yaml)."""

    robot_id: str = Field(default="g1", pattern=r"^[A-Za-z0-9_\-]+$", max_length=64)
    bus: BusConfig = Field(default_factory=BusConfig)
    robot: RobotConfig = Field(default_factory=RobotConfig)
    retargeting: RetargetingConfig = Field(default_factory=RetargetingConfig)
    safety: SafetyConfig = Field(default_factory=SafetyConfig)
    executor: ExecutorConfig = Field(default_factory=ExecutorConfig)
    api: ApiConfig = Field(default_factory=ApiConfig)
    perception: PerceptionConfig = Field(default_factory=PerceptionConfig)
    human: HumanConfig = Field(default_factory=HumanConfig)


#: Readable forms of the patterns a text field must match (for errors: the regex says little).
_PATTERN_HINTS = {PLACEMENT_PATTERN: "auto, side-by-side, facing, recorded or x,y,yaw (m, m, rad)"}

#: Where a bad field's value came from, by its location in the data (for errors).
Source = Callable[[tuple[str | int, ...]], str]


def _format_validation_error(exc: ValidationError, origin: str, source: Source | None = None) -> str:
    """One line per bad field: its dotted name, where its value came from (``source``; else the
    header's ``origin``), what is wrong and the value given."""
    lines = [f"invalid configuration ({origin}):" if source is None else "invalid configuration:"]
    for err in exc.errors(include_url=False):
        loc = tuple(err["loc"])
        field = ".".join(str(p) for p in loc) or "<root>"
        where = "" if source is None else f" (from {source(loc)})"
        ctx, given = err.get("ctx") or {}, err.get("input")
        hint = _PATTERN_HINTS.get(ctx.get("pattern", ""))
        if err["type"] == "string_pattern_mismatch" and hint:
            message = f"expected {hint}"
        elif err["type"] == "value_error":  # a validator's own words, without pydantic's "Value error, "
            message = str(ctx.get("error", err["msg"]))
        else:
            message = err["msg"]
        got = "" if err["type"] == "value_error" and isinstance(given, Mapping) else f" (got {given!r:.80})"
        lines.append(f"  {field}{where}: {message}{got}")
    return "\n".join(lines)


def _holds(tree: Mapping[str, Any], loc: tuple[str | int, ...]) -> bool:
    """Whether the nested ``tree`` sets something at or below ``loc`` (a list index ends the walk)."""
    node: Any = tree
    for key in loc:
        if not isinstance(node, Mapping) or key not in node:
            return isinstance(key, int) and node is not tree
        node = node[key]
    return True


def env_overrides(environ: Mapping[str, str]) -> dict[str, Any]:
    """Nested dict from ``SAFEMIMIC__A__B=value`` variables (keys lower-cased, values parsed as YAML)."""
    tree: dict[str, Any] = {}
    for key, raw in environ.items():
        if not key.startswith(ENV_PREFIX):
            continue
        path = [part.lower() for part in key[len(ENV_PREFIX) :].split("__")]
        if not all(path):
            raise ConfigError(f"malformed override variable {key!r}")
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError as exc:
            raise ConfigError(f"{'.'.join(path)}: cannot parse {key}={raw!r}: {exc}") from None
        node = tree
        for part in path[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{key} conflicts with another override")
        node[path[-1]] = value
    return tree


def deep_merge(base: Mapping[str, Any], patch: Mapping[str, Any]) -> dict[str, Any]:
    """A new dict: ``base`` with ``patch`` merged in recursively (patch wins on leaves)."""
    merged = copy.deepcopy(dict(base))
    for key, value in patch.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = copy.deepcopy(value)
    return merged


def validate_config(data: Mapping[str, Any], origin: str = "config", source: Source | None = None) -> StackConfig:
    """Validate a nested dict into a :class:`StackConfig`; :class:`ConfigError` names the bad fields
    and where their values came from (``source`` of each field's location; else ``origin``)."""
    try:
        return StackConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_format_validation_error(exc, origin, source)) from None


def read_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping; :class:`ConfigError` if missing, unparsable or not a mapping."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path} is not UTF-8 text: {exc}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path} is not valid YAML: {exc}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path} must hold a mapping at top level, not {type(data).__name__}")
    return data


def load_config(
    path: str | Path | None = None,
    environ: Mapping[str, str] | None = None,
    overrides: Mapping[str, Any] | None = None,
) -> StackConfig:
    """Load the stack configuration: file, then environment overrides, then ``overrides`` (the
    command line's options). A :class:`ConfigError` names each bad field with where its value came
    from: the command line, the ``SAFEMIMIC__…`` variables that set it, or the file."""
    environ = os.environ if environ is None else environ
    path = Path(path or environ.get(CONFIG_ENV) or DEFAULT_CONFIG_PATH)
    from_env = env_overrides(environ)
    data = deep_merge(read_yaml(path), from_env)
    if overrides:
        data = deep_merge(data, overrides)

    def source(loc: tuple[str | int, ...]) -> str:
        if overrides and _holds(overrides, loc):
            return "the command line"
        if _holds(from_env, loc):
            named = [key for key in environ if key.startswith(ENV_PREFIX)
                     and _holds(env_overrides({key: environ[key]}), loc)]
            return ", ".join(f"${key}" for key in sorted(named))
        return str(path)

    return validate_config(data, origin=str(path), source=source)


def resolve_config_path(relative: str | Path, base: Path = CONFIG_DIR) -> Path:
    """Absolute path of a file named in the configuration (relative paths: against ``base``)."""
    path = Path(relative).expanduser()
    return path if path.is_absolute() else (base / path).resolve()
