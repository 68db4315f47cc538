"""The single writer: validate a change on the whole configuration, persist it, publish it, wait
until the safety service reports it applied. Changes are serialised; a refused or unpersistable
change leaves the current configuration, the file and the bus untouched."""

from __future__ import annotations

import asyncio
import copy
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from services.config_api.link import BusLink
from services.config_api.models import REQUEST_FIELD, ChangeResponse
from services.config_api.store import ConfigStore
from shared.config import StackConfig


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


def _request_errors(exc: ValidationError) -> list[dict[str, Any]]:
    """Errors found on the whole configuration, located at the request field that caused them."""
    errors = []
    for error in exc.errors(include_url=False, include_context=False):
        path = ".".join(str(part) for part in error["loc"])
        field = next((REQUEST_FIELD[p] for p in REQUEST_FIELD if path == p or path.startswith(p + ".")), path)
        errors.append({**error, "loc": ["body", *field.split(".")]})
    return errors


class ConfigWriter:
    """Applies changes to the stored configuration, one at a time."""

    def __init__(self, store: ConfigStore, link: BusLink, ack_timeout_s: float) -> None:
        self.store = store
        self.link = link
        self.ack_timeout_s = ack_timeout_s
        self._lock = asyncio.Lock()

    async def change(self, changes: Mapping[str, Any], actor: Actor, action: str) -> ChangeResponse:
        """Set ``changes`` (dotted configuration path → value) and make the result the next version.

        Raises ``RequestValidationError`` (422) if the result is invalid, and
        :class:`~services.config_api.store.StoreError` if it cannot be persisted.
        """
        async with self._lock:
            current = self.store.snapshot
            try:
                new = StackConfig.model_validate(with_changes(current.config.model_dump(mode="json"), changes))
            except ValidationError as exc:
                raise RequestValidationError(_request_errors(exc)) from None
            entry = await asyncio.to_thread(
                self.store.commit, new, actor.who, actor.client, action, self.link.highest_version_seen
            )
            if entry is None:
                version = current.version
                return self._response(version, self.link.applied(version, 0.0), [], "nothing to change")
            published = time.monotonic()
            changed = [change.path for change in entry.diff]
            version, config = self.store.published()
            self.link.publish(version, changed, config)
        applied = await self.link.wait_applied(entry.version, published, self.ack_timeout_s)
        detail = (
            f"v{entry.version} applied by the safety service" if applied else
            f"v{entry.version} saved and published; no safety service acknowledged it within {self.ack_timeout_s:g} s"
        )
        return self._response(entry.version, applied, changed, detail)

    def _response(self, version: int, applied: bool, changed: list[str], detail: str) -> ChangeResponse:
        status = self.link.status.get()
        acknowledged = None if status is None else status.message.config_version
        return ChangeResponse(version=version, applied=applied, changed=changed, acknowledged_version=acknowledged, detail=detail)
