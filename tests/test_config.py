"""Stack configuration: shipped defaults, environment overrides, error messages naming fields."""

from __future__ import annotations

import copy
import os
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import BaseModel

from shared.codec import MAX_MESSAGE_BYTES
from shared.config import (
    CONFIG_DIR,
    CONFIG_ENV,
    DEFAULT_CONFIG_PATH,
    BusMode,
    ConfigError,
    QPBackendName,
    StackConfig,
    deep_merge,
    env_overrides,
    load_config,
    read_yaml,
    resolve_config_path,
    validate_config,
)
from shared.names import IMITATION_JOINT_NAMES

# --------------------------------------------------------------------------------------------
# shipped defaults


def test_defaults_from_shipped_yaml() -> None:
    cfg = load_config(environ={})
    assert DEFAULT_CONFIG_PATH == CONFIG_DIR / "default.yaml" and DEFAULT_CONFIG_PATH.is_file()
    assert cfg.robot_id == "g1"
    assert cfg.safety.rate_hz == 500.0
    assert cfg.safety.status_rate_hz == 50.0
    assert cfg.safety.backend is QPBackendName.DAQP
    assert cfg.safety.gamma == 10.0 and cfg.safety.phi == 0.02 and cfg.safety.gain == 8.0
    assert cfg.safety.weights == [1.0] * 8
    # the YAML's per-joint speed limits (not the model's uniform default): waist slower than arms
    assert cfg.safety.u_max == [3.0, 3.0, 10.0, 10.0, 10.0, 10.0, 10.0, 10.0]
    assert cfg.safety.human_velocity_term is True and cfg.safety.human_timeout_s == 0.5
    assert cfg.safety.pairs == "default"
    assert cfg.bus.mode is BusMode.PEER and cfg.bus.connect == [] and cfg.bus.listen == []
    assert cfg.bus.lease_ms == 500  # architecture §11: a vanished service noticed within 1 s (≈ 0.5 s)
    assert cfg.bus.max_message_bytes == 262144  # far below Zenoh's 1 GiB default
    assert cfg.retargeting.scale == [1.0] * 8 and cfg.retargeting.offset == [0.0] * 8
    assert cfg.retargeting.theta_home == [0.0] * 8 and cfg.retargeting.mirror is False
    assert cfg.robot.spec == "robots/g1.yaml" and cfg.robot.model is None
    assert cfg.executor.rate_hz == 500.0 and cfg.executor.state_rate_hz == 200.0
    assert cfg.executor.command_timeout_s == 0.2 and cfg.executor.viewer is False
    assert cfg.api.host == "127.0.0.1" and cfg.api.port == 8080 and cfg.api.store is None


def test_shipped_yaml_sets_every_field() -> None:
    """default.yaml documents the whole configuration: every section and field appears in it."""
    raw = read_yaml(DEFAULT_CONFIG_PATH)
    assert set(raw) == set(StackConfig.model_fields)
    cfg = StackConfig.model_validate(raw)
    for section_name in StackConfig.model_fields:
        section = getattr(cfg, section_name)
        if isinstance(section, BaseModel):
            missing = set(type(section).model_fields) - set(raw[section_name])
            assert not missing, f"default.yaml lacks {section_name}.{sorted(missing)}"


def test_shipped_files_referenced_by_defaults_exist() -> None:
    cfg = load_config(environ={})
    spec = resolve_config_path(cfg.robot.spec)
    assert spec == (CONFIG_DIR / "robots" / "g1.yaml").resolve()
    assert spec.is_file()
    absolute = Path("/somewhere/else.yaml")
    assert resolve_config_path(absolute) == absolute


def test_bus_limit_admits_every_codec_message() -> None:
    # a message the codec may produce must fit through the bus
    assert load_config(environ={}).bus.max_message_bytes >= MAX_MESSAGE_BYTES


def test_vectors_have_one_entry_per_joint() -> None:
    cfg = load_config(environ={})
    for vector in (cfg.safety.weights, cfg.safety.u_max, cfg.retargeting.scale, cfg.retargeting.offset):
        assert len(vector) == len(IMITATION_JOINT_NAMES)


def test_load_config_reads_os_environ_by_default(monkeypatch: pytest.MonkeyPatch) -> None:
    for key in list(os.environ):
        if key.startswith("SAFEMIMIC"):
            monkeypatch.delenv(key)
    assert load_config() == load_config(environ={})
    monkeypatch.setenv("SAFEMIMIC__SAFETY__PHI", "0.05")
    assert load_config().safety.phi == 0.05


def test_config_survives_json_round_trip() -> None:
    """The config API ships StackConfig as JSON inside ConfigUpdate: it must validate back unchanged."""
    cfg = load_config(environ={"SAFEMIMIC__BUS__CONNECT": '["tcp/127.0.0.1:7447"]'})
    assert validate_config(cfg.model_dump(mode="json")) == cfg


# --------------------------------------------------------------------------------------------
# environment overrides


def test_env_override_scalar() -> None:
    cfg = load_config(environ={"SAFEMIMIC__SAFETY__GAMMA": "5"})
    assert cfg.safety.gamma == 5.0 and isinstance(cfg.safety.gamma, float)
    default = load_config(environ={})
    assert cfg.safety.model_dump(exclude={"gamma"}) == default.safety.model_dump(exclude={"gamma"})
    assert cfg.model_dump(exclude={"safety"}) == default.model_dump(exclude={"safety"})


def test_env_override_list_bool_enum_and_null() -> None:
    cfg = load_config(
        environ={
            "SAFEMIMIC__BUS__CONNECT": '["tcp/127.0.0.1:7447"]',
            "SAFEMIMIC__BUS__LISTEN": "[tcp/0.0.0.0:7448, udp/0.0.0.0:7449]",
            "SAFEMIMIC__BUS__MULTICAST_SCOUTING": "false",
            "SAFEMIMIC__BUS__MODE": "client",
            "SAFEMIMIC__SAFETY__BACKEND": "osqp",
            "SAFEMIMIC__SAFETY__U_MAX": "[1, 1, 2, 2, 2, 2, 2, 2]",
            "SAFEMIMIC__API__STORE": "/tmp/x.yaml",
            "SAFEMIMIC__ROBOT_ID": "g1_lab",
            "PATH": "/usr/bin",  # unrelated variables are ignored
            "SAFEMIMIC_OTHER": "ignored",
        }
    )
    assert cfg.bus.connect == ["tcp/127.0.0.1:7447"]
    assert cfg.bus.listen == ["tcp/0.0.0.0:7448", "udp/0.0.0.0:7449"]
    assert cfg.bus.multicast_scouting is False
    assert cfg.bus.mode is BusMode.CLIENT
    assert cfg.safety.backend is QPBackendName.OSQP
    assert cfg.safety.u_max == [1.0, 1.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0]
    assert cfg.api.store == "/tmp/x.yaml"
    assert cfg.robot_id == "g1_lab"


def test_env_override_keys_are_case_insensitive() -> None:
    assert load_config(environ={"SAFEMIMIC__safety__Gamma": "7"}).safety.gamma == 7.0


def test_env_overrides_tree() -> None:
    tree = env_overrides({"SAFEMIMIC__SAFETY__GAMMA": "5", "SAFEMIMIC__SAFETY__PHI": "0.1", "HOME": "/root"})
    assert tree == {"safety": {"gamma": 5, "phi": 0.1}}
    assert env_overrides({}) == {}


def test_explicit_overrides_win_over_environment() -> None:
    cfg = load_config(environ={"SAFEMIMIC__SAFETY__GAMMA": "5"}, overrides={"safety": {"gamma": 6.0}})
    assert cfg.safety.gamma == 6.0


@pytest.mark.parametrize(
    ("environ", "needle"),
    [
        ({"SAFEMIMIC__SAFETY__BOGUS": "1"}, "safety.bogus"),
        ({"SAFEMIMIC__BUS__LEASE_MSS": "1"}, "bus.lease_mss"),
        ({"SAFEMIMIC__NOPE__X": "1"}, "nope"),
        ({"SAFEMIMIC__SAFETY__GAMMA__DEEP": "1"}, "safety.gamma"),
        ({"SAFEMIMIC__SAFETY__GAMMA": "-1"}, "safety.gamma"),
        ({"SAFEMIMIC__SAFETY__GAMMA": ".nan"}, "safety.gamma"),
        ({"SAFEMIMIC__SAFETY__GAMMA": ".inf"}, "safety.gamma"),
        ({"SAFEMIMIC__SAFETY__GAMMA": "fast"}, "safety.gamma"),
        ({"SAFEMIMIC__BUS__CONNECT": "[unclosed"}, "bus.connect"),
        ({"SAFEMIMIC__BUS__CONNECT": "tcp/1.2.3.4:7447"}, "bus.connect"),  # a string, not a list
        ({"SAFEMIMIC__SAFETY__": "1"}, "SAFEMIMIC__SAFETY__"),
        ({"SAFEMIMIC__": "1"}, "SAFEMIMIC__"),
        ({"SAFEMIMIC____GAMMA": "1"}, "SAFEMIMIC____GAMMA"),
    ],
)
def test_bad_env_override_names_it(environ: dict[str, str], needle: str) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(environ=environ)
    assert needle in str(info.value)


@pytest.mark.parametrize("order", ["section_first", "field_first"])
def test_conflicting_env_overrides_error(order: str) -> None:
    items = [("SAFEMIMIC__SAFETY", "1"), ("SAFEMIMIC__SAFETY__GAMMA", "5")]
    environ = dict(items if order == "section_first" else items[::-1])
    with pytest.raises(ConfigError, match="SAFETY|safety"):
        load_config(environ=environ)


# --------------------------------------------------------------------------------------------
# bad values name their field


@pytest.mark.parametrize(
    ("overrides", "needle"),
    [
        ({"safety": {"gamma": -1}}, "safety.gamma"),
        ({"safety": {"gamma": 0}}, "safety.gamma"),
        ({"safety": {"gamma": float("nan")}}, "safety.gamma"),
        ({"safety": {"phi": 1.0}}, "safety.phi"),
        ({"safety": {"rate_hz": 0}}, "safety.rate_hz"),
        ({"safety": {"weights": [1.0] * 7}}, "safety.weights"),
        ({"safety": {"weights": [1.0] * 9}}, "safety.weights"),
        ({"safety": {"u_max": "fast"}}, "safety.u_max"),
        ({"safety": {"backend": "cplex"}}, "safety.backend"),
        ({"safety": {"pairs": "Bad Pairs!"}}, "safety.pairs"),
        ({"retargeting": {"scale": [1.0] * 7}}, "retargeting.scale"),
        ({"retargeting": {"offset": [0.0] * 7 + [float("inf")]}}, "retargeting.offset"),
        ({"bus": {"mode": "mesh"}}, "bus.mode"),
        ({"bus": {"lease_ms": 10}}, "bus.lease_ms"),
        ({"bus": {"max_message_bytes": 2**40}}, "bus.max_message_bytes"),
        ({"api": {"port": 70000}}, "api.port"),
        ({"executor": {"kp": -1}}, "executor.kp"),
        ({"executor": {"stop_damping": 0.5}}, "executor.stop_damping"),
        ({"executor": {"stop_damping": float("nan")}}, "executor.stop_damping"),
        ({"executor": {"g1": {"stop_damping": 6.0}}}, "executor.g1.stop_damping"),
        ({"robot_id": "bad id/with slash"}, "robot_id"),
        ({"nonsense": {"a": 1}}, "nonsense"),
        ({"safety": {"gama": 5}}, "safety.gama"),
        ({"safety": 5}, "safety"),
    ],
)
def test_bad_value_names_its_field(overrides: dict[str, Any], needle: str) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(environ={}, overrides=overrides)
    message = str(info.value)
    assert needle in message
    assert "(from the command line)" in message  # and where the bad value came from


def test_each_bad_field_names_where_its_value_came_from(tmp_path: Path) -> None:
    """The file, the variable that set it, or the command line: not always the file."""
    path = tmp_path / "site.yaml"
    path.write_text("safety:\n  phi: 3.0\n")
    environ = {"SAFEMIMIC__SAFTY__GAMMA": "5", "SAFEMIMIC__BUS__LEASE_MS": "10"}
    with pytest.raises(ConfigError) as info:
        load_config(path, environ=environ, overrides={"perception": {"placement": "sideways"}})
    lines = str(info.value).splitlines()
    assert lines[0] == "invalid configuration:"
    assert any(line.startswith(f"  safety.phi (from {path}): ") for line in lines), lines
    assert any(line.startswith("  safty (from $SAFEMIMIC__SAFTY__GAMMA): ") for line in lines), lines
    assert any(line.startswith("  bus.lease_ms (from $SAFEMIMIC__BUS__LEASE_MS): ") for line in lines), lines
    placement = next(line for line in lines if line.startswith("  perception.placement (from the command line): "))
    assert "expected auto, side-by-side, facing, recorded or x,y,yaw" in placement and "'sideways'" in placement
    assert "^(?:" not in str(info.value)  # the readable form, not the pattern


@pytest.mark.parametrize("endpoint", ["tcp/10.0.0.2:7447", "tls/robot.local:7447", "tcp/[::1]:7447",
                                      "udp/0.0.0.0:7449", "tcp/127.0.0.1:7447?iface=eth0", "tcp/0.0.0.0:0",
                                      "unixsock-stream//tmp/safemimic.sock"])
def test_zenoh_endpoints_are_accepted(endpoint: str) -> None:
    bus = load_config(environ={}, overrides={"bus": {"connect": [endpoint], "listen": [endpoint]}}).bus
    assert bus.connect == [endpoint] and bus.listen == [endpoint]


@pytest.mark.parametrize("endpoint", ["192.168.1.10:7447", "garbage", "tcp/", "tcp/10.0.0.2", "tcp/10.0.0.2:",
                                      "tcp/10.0.0.2:65536", "tcp/10.0.0.2:port", "TCP/10.0.0.2:7447",
                                      "tcp/10.0.0.2:7447 ", "tls/robot local:7447"])
@pytest.mark.parametrize("field", ["connect", "listen"])
def test_a_malformed_endpoint_is_a_configuration_error_naming_it(endpoint: str, field: str) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(environ={}, overrides={"bus": {field: ["tcp/10.0.0.2:7447", endpoint]}})
    message = str(info.value)
    assert f"bus.{field}.1 (from the command line): {endpoint!r} is not a Zenoh endpoint" in message, message
    assert "Value error" not in message


def test_non_positive_weight_names_section_and_field() -> None:
    for field in ("weights", "u_max"):
        with pytest.raises(ConfigError) as info:
            load_config(environ={}, overrides={"safety": {field: [1.0] * 7 + [0.0]}})
        assert "safety" in str(info.value) and field in str(info.value)


def test_validate_config_reports_every_bad_field_and_origin() -> None:
    with pytest.raises(ConfigError) as info:
        validate_config({"safety": {"gamma": -1, "phi": -1}, "api": {"port": -5}}, origin="update #7")
    message = str(info.value)
    for needle in ("update #7", "safety.gamma", "safety.phi", "api.port"):
        assert needle in message


# --------------------------------------------------------------------------------------------
# files


def write(path: Path, text: str | bytes) -> Path:
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    return path


def test_safemimic_config_selects_another_file(tmp_path: Path) -> None:
    other = write(tmp_path / "lab.yaml", "robot_id: lab_g1\nsafety:\n  gamma: 3\n  backend: osqp\n")
    cfg = load_config(environ={CONFIG_ENV: str(other)})
    assert cfg.robot_id == "lab_g1" and cfg.safety.gamma == 3.0 and cfg.safety.backend is QPBackendName.OSQP
    # fields the file leaves out take the model defaults, not default.yaml's values (equal for now)
    assert cfg.safety.u_max == StackConfig().safety.u_max and cfg.safety.phi == StackConfig().safety.phi
    # environment overrides still apply on top of the selected file
    cfg = load_config(environ={CONFIG_ENV: str(other), "SAFEMIMIC__SAFETY__GAMMA": "4"})
    assert cfg.safety.gamma == 4.0 and cfg.robot_id == "lab_g1"
    # an explicit path wins over $SAFEMIMIC_CONFIG
    assert load_config(DEFAULT_CONFIG_PATH, environ={CONFIG_ENV: str(other)}).robot_id == "g1"
    # errors name the selected file
    bad = write(tmp_path / "bad.yaml", "safety:\n  gamma: -2\n")
    with pytest.raises(ConfigError) as info:
        load_config(environ={CONFIG_ENV: str(bad)})
    assert str(bad) in str(info.value) and "safety.gamma" in str(info.value)


def test_empty_file_gives_model_defaults(tmp_path: Path) -> None:
    empty = write(tmp_path / "empty.yaml", "# nothing\n")
    assert load_config(empty, environ={}) == StackConfig()


@pytest.mark.parametrize(
    "content",
    ["- a\n- b\n", "42\n", "just a string\n", "[1, 2]\n"],
    ids=["list", "int", "str", "flow-list"],
)
def test_yaml_not_a_mapping(tmp_path: Path, content: str) -> None:
    path = write(tmp_path / "notmap.yaml", content)
    with pytest.raises(ConfigError) as info:
        load_config(path, environ={})
    assert str(path) in str(info.value) and "mapping" in str(info.value)


@pytest.mark.parametrize(
    "content",
    [
        "safety: [unclosed\n",
        "safety:\n  gamma: 1\n gain: 2\n",  # bad indentation
        "a: b: c\n",
        "key: !!python/object:os.system 'echo hi'\n",  # safe_load refuses arbitrary tags
        b"safety:\n  gamma: \xff\xfe\n",  # not UTF-8
    ],
    ids=["unclosed", "indent", "colon", "unsafe-tag", "not-utf8"],
)
def test_invalid_yaml_names_the_path(tmp_path: Path, content: str | bytes) -> None:
    path = write(tmp_path / "broken.yaml", content)
    with pytest.raises(ConfigError) as info:
        load_config(path, environ={})
    assert str(path) in str(info.value)


def test_unreadable_paths(tmp_path: Path) -> None:
    missing = tmp_path / "does" / "not" / "exist.yaml"
    with pytest.raises(ConfigError) as info:
        load_config(missing, environ={})
    assert str(missing) in str(info.value)
    with pytest.raises(ConfigError) as info:  # a directory
        load_config(tmp_path, environ={})
    assert str(tmp_path) in str(info.value)
    with pytest.raises(ConfigError) as info:  # selected through the environment
        load_config(environ={CONFIG_ENV: str(missing)})
    assert str(missing) in str(info.value)


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root reads any file")
def test_permission_denied(tmp_path: Path) -> None:
    path = write(tmp_path / "secret.yaml", "robot_id: g1\n")
    path.chmod(0)
    try:
        with pytest.raises(ConfigError) as info:
            load_config(path, environ={})
        assert str(path) in str(info.value)
    finally:
        path.chmod(0o600)


def test_round_trip_through_a_yaml_file(tmp_path: Path) -> None:
    cfg = load_config(environ={}, overrides={"safety": {"gamma": 2.5}, "bus": {"connect": ["tcp/10.0.0.2:7447"]}})
    path = write(tmp_path / "dump.yaml", yaml.safe_dump(cfg.model_dump(mode="json")))
    assert load_config(path, environ={}) == cfg


# --------------------------------------------------------------------------------------------
# deep_merge


def test_deep_merge_merges_and_does_not_mutate() -> None:
    base = {"safety": {"gamma": 10.0, "weights": [1.0, 2.0]}, "bus": {"connect": ["a"]}, "robot_id": "g1"}
    patch = {"safety": {"gamma": 5.0, "extra": {"deep": [1]}}, "bus": "replaced", "api": {"port": 1}}
    base_before, patch_before = copy.deepcopy(base), copy.deepcopy(patch)
    merged = deep_merge(base, patch)
    assert merged == {
        "safety": {"gamma": 5.0, "weights": [1.0, 2.0], "extra": {"deep": [1]}},
        "bus": "replaced",
        "robot_id": "g1",
        "api": {"port": 1},
    }
    assert base == base_before and patch == patch_before
    # no aliasing: mutating the result leaves the inputs alone
    merged["safety"]["weights"].append(3.0)
    merged["safety"]["extra"]["deep"].append(2)
    merged["api"]["port"] = 2
    assert base == base_before and patch == patch_before
    # a mapping replaces a scalar, and the other way round
    assert deep_merge({"a": 1}, {"a": {"b": 2}}) == {"a": {"b": 2}}
    assert deep_merge({"a": {"b": 2}}, {"a": 1}) == {"a": 1}
    assert deep_merge({}, {}) == {}


JSONISH = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=5),
    lambda children: st.lists(children, max_size=3) | st.dictionaries(st.text(max_size=3), children, max_size=3),
    max_leaves=12,
)
TREES = st.dictionaries(st.text(max_size=3), JSONISH, max_size=4)


def _check_merge(base: dict, patch: dict, merged: dict) -> None:
    """The recursive specification: patch wins on leaves, mappings merge, base-only keys survive."""
    assert set(merged) == set(base) | set(patch)
    for key, value in merged.items():
        if key not in patch:
            assert value == base[key]
        elif isinstance(patch[key], dict) and isinstance(base.get(key), dict):
            _check_merge(base[key], patch[key], value)
        else:
            assert value == patch[key]


@settings(max_examples=200, deadline=None)
@given(TREES, TREES)
def test_deep_merge_properties(base: dict, patch: dict) -> None:
    base_before, patch_before = copy.deepcopy(base), copy.deepcopy(patch)
    merged = deep_merge(base, patch)
    assert base == base_before and patch == patch_before
    _check_merge(base, patch, merged)
    assert deep_merge(merged, patch) == merged  # idempotent
    assert deep_merge(base, {}) == base and deep_merge({}, patch) == patch


def test_feedforward_extrapolation_and_velocity_bounds_within_the_g1_limits() -> None:
    """Feed-forward on by default (off: the paper's eq. 7), extrapolation bounded, and the
    velocity bounds within the G1's published joint velocity limits read from the robot description."""
    from shared.robot_spec import configured_robot_spec

    conf = load_config(environ={})
    assert conf.safety.feedforward is True and 0 < conf.safety.extrapolate_max_s <= 0.05
    assert load_config(environ={"SAFEMIMIC__SAFETY__FEEDFORWARD": "false"}).safety.feedforward is False
    for bad in (-0.01, 0.6):
        with pytest.raises(ConfigError):
            load_config(environ={}, overrides={"safety": {"extrapolate_max_s": bad}})
    spec = configured_robot_spec(conf)
    assert spec.velocity_limits() == [37.0] * 8  # unitree_ros g1_29dof_rev_1_0.urdf: velocity="37"
    spec.check_velocity_bounds(conf.safety.u_max, conf.safety.u_min)
    assert max(conf.safety.u_max) > 4.0, "faster than the old 4 rad/s that saturated on punches"
    with pytest.raises(ValueError, match="left_elbow_joint 40"):
        spec.check_velocity_bounds([3.0, 3.0, 10.0, 10.0, 40.0, 10.0, 10.0, 10.0])
    with pytest.raises(ValueError, match="waist_roll_joint 38"):
        spec.check_velocity_bounds(conf.safety.u_max, [-38.0] + [-1.0] * 7)
    raw = spec.model_dump()
    for bad_limits in ({"left_wrist_pitch_joint": 22.0}, {"waist_roll_joint": 0.0}):
        with pytest.raises(ValueError):
            type(spec).model_validate({**raw, "joint_velocity_limits": bad_limits})
