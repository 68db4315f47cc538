"""The single writer: validate a change on the whole configuration, persist it, publish it, wait
until the safety service reports it applied. Changes are serialised, each computed from the
configuration it replaces (inside the lock: two concurrent patches of one mapping, such as the
robot's capsule radii, both land); a refused or unpersistable change leaves the current
configuration, the file and the bus untouched.

Validated as the safety service validates an update, so that nothing it would refuse is saved
(a refused version would stay in the store and every later change would carry it): the
configuration's own rules, and the velocity bounds within the robot's ``joint_velocity_limits``
(:meth:`~shared.robot_spec.RobotSpec.check_velocity_bounds`)."""

from __future__ import annotations

import asyncio
import copy
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from services.config_api.link import BusLink
from services.config_api.models import REQUEST_FIELD, ChangeResponse
from services.config_api.store import ConfigStore
from shared.config import StackConfig
from shared.robot_spec import RobotSpec

#: The changes a request makes (dotted configuration path → value), from the configuration they replace.
Changes = Callable[[StackConfig], Mapping[str, Any]]


@dataclass(frozen=True)
class Actor:
    """Who asks for a change: the operator's name (X-Operator header) and the client's address."""

    who: str
    client: str


def with_changes(tree: Mapping[str, Any], changes: Mapping[str, Any]) -> dict[str, Any]:
    """A copy of the JSON tree ``tree`` with each dotted path of ``changes`` set (replaced) to its value."""
    data = copy.deepcopy(dict(tree))
    for path, value in changes.items():
        *parents, leaf = path.split(".")
        node = data
        for part in parents:
            node = node[part]
        node[leaf] = value
    return data


def _robot_errors(conf: StackConfig, spec: RobotSpec) -> list[dict[str, Any]]:
    """The velocity bounds of ``conf`` beyond the robot's ``joint_velocity_limits`` (``spec``), as
    request errors at ``u_max`` / ``u_min`` (the safety service refuses such an update)."""
    errors = []
    for name, bound in (("u_max", conf.safety.u_max), ("u_min", conf.safety.u_min)):
        try:
            if bound is not None:
                spec.check_velocity_bounds([abs(v) for v in bound])
        except ValueError as exc:
            errors.append({"type": "value_error", "loc": ["body", name], "msg": str(exc), "input": bound})
    return errors


def _request_errors(exc: ValidationError) -> list[dict[str, Any]]:
    """Errors found on the whole configuration, located at the request field that caused them."""
    errors = []
    for error in exc.errors(include_url=False, include_context=False):
        path = ".".join(str(part) for part in error["loc"])
        field = next((REQUEST_FIELD[p] for p in REQUEST_FIELD if path == p or path.startswith(p + ".")), path)
        errors.append({**error, "loc": ["body", *field.split(".")]})
    return errors


class ConfigWriter:
    """Applies changes to the stored configuration, one at a time; ``spec`` the robot the configuration
    drives (its velocity limits bound every change: module docstring)."""

    def __init__(self, store: ConfigStore, link: BusLink, ack_timeout_s: float, spec: RobotSpec) -> None:
        self.store = store
        self.link = link
        self.ack_timeout_s = ack_timeout_s
        self.spec = spec
        self._lock = asyncio.Lock()

    async def change(self, changes: Changes, actor: Actor, action: str) -> ChangeResponse:
        """Set ``changes(current)`` (dotted configuration path → value; ``current`` the configuration
        they replace) and make the result the next version.

        Raises ``RequestValidationError`` (422) if the result is invalid (module docstring), and
        :class:`~services.config_api.store.StoreError` if it cannot be persisted.
        """
        async with self._lock:
            current = self.store.snapshot
            try:
                new = StackConfig.model_validate(with_changes(current.config.model_dump(mode="json"),
                                                              changes(current.config)))
            except ValidationError as exc:
                raise RequestValidationError(_request_errors(exc)) from None
            if errors := _robot_errors(new, self.spec):
                raise RequestValidationError(errors)
            entry = await asyncio.to_thread(
                self.store.commit, new, actor.who, actor.client, action, self.link.highest_version_seen
            )
            if entry is None:
                version = current.version
                return self._response(version, self.link.applied(version, 0.0), [], "nothing to change")
            published = time.monotonic()
            refused_before = self._config_refusals()
            changed = [change.path for change in entry.diff]
            version, config = self.store.published()
            self.link.publish(version, changed, config)
        applied = await self.link.wait_applied(entry.version, published, self.ack_timeout_s)
        return self._response(entry.version, applied, changed, self._detail(entry.version, applied, published,
                                                                          refused_before))

    def _config_refusals(self) -> int:
        """The configuration updates the safety service has refused so far (its status's ``dropped``)."""
        status = self.link.status.get()
        return 0 if status is None else status.message.dropped.get("config", 0)

    def _detail(self, version: int, applied: bool, published: float, refused_before: int) -> str:
        """What became of version ``version``, published at monotonic time ``published``: applied, refused
        by the safety service (its refusal count grew since), or not acknowledged (no status since)."""
        if applied:
            return f"v{version} applied by the safety service"
        status = self.link.status.get()
        if status is not None and status.received >= published and self._config_refusals() > refused_before:
            return (f"v{version} saved and published; the safety service refused it and runs "
                    f"v{status.message.config_version} (its log says why)")
        if status is None or status.received < published:
            return f"v{version} saved and published; no safety service is reporting"
        return f"v{version} saved and published; no safety service acknowledged it within {self.ack_timeout_s:g} s"

    def _response(self, version: int, applied: bool, changed: list[str], detail: str) -> ChangeResponse:
        status = self.link.status.get()
        acknowledged = None if status is None else status.message.config_version
        return ChangeResponse(version=version, applied=applied, changed=changed, acknowledged_version=acknowledged, detail=detail)
