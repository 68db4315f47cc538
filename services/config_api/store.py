"""The persisted, versioned configuration: one JSON file written atomically, with a history.

The file holds the whole validated :class:`~shared.config.StackConfig` (the API token never),
its version and the last accepted changes. On load, the process's own deployment sections
(:data:`LOCAL_SECTIONS`: robot id, bus, API server) come from the startup configuration, every
other section from the file: the store is the source of truth once a change was accepted.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from services.config_api.errors import ConfigApiError
from shared.config import ConfigError, StackConfig, validate_config

STORE_FORMAT = "safemimic.config-store/1"
#: Sections that describe this process's deployment: never persisted over, never changed by the API.
LOCAL_SECTIONS = ("robot_id", "bus", "api")


class StoreError(ConfigApiError, RuntimeError):
    """The store file cannot be read, parsed or written (the message names the file)."""


class Change(BaseModel):
    """One changed leaf of the configuration (dotted path; lists compare as a whole)."""

    path: str
    old: Any = None
    new: Any = None


class HistoryEntry(BaseModel):
    """An accepted change: who made it, when, and what changed."""

    model_config = ConfigDict(extra="forbid")
    version: int = Field(ge=1)
    time: datetime
    who: str = Field(max_length=64, description="the X-Operator header, or 'operator'")
    client: str = Field(max_length=64, description="network address of the client")
    action: str = Field(max_length=64, description="the endpoint's action, e.g. 'patch safety', 'calibrate'")
    diff: list[Change]


class StoreFile(BaseModel):
    """The store file's content."""

    model_config = ConfigDict(extra="forbid")
    format: Literal["safemimic.config-store/1"] = STORE_FORMAT
    version: int = Field(ge=0)
    updated_at: datetime | None = None
    config: dict[str, Any]
    history: list[HistoryEntry] = Field(default_factory=list)


@dataclass(frozen=True)
class Snapshot:
    """The current accepted configuration (replaced as a whole on every commit)."""

    version: int
    config: StackConfig
    updated_at: datetime | None
    history: tuple[HistoryEntry, ...]


def public_config(conf: StackConfig) -> StackConfig:
    """``conf`` without secrets: what is persisted, published and shown."""
    return conf.model_copy(update={"api": conf.api.model_copy(update={"token": None})})


def config_diff(old: Any, new: Any, prefix: str = "") -> list[Change]:
    """Changed leaves between two JSON trees, as dotted paths (dicts recurse, anything else is a leaf)."""
    if isinstance(old, dict) and isinstance(new, dict):
        changes: list[Change] = []
        for key in sorted(set(old) | set(new), key=str):
            changes += config_diff(old.get(key), new.get(key), f"{prefix}.{key}" if prefix else str(key))
        return changes
    return [] if old == new else [Change(path=prefix, old=old, new=new)]


#: Suffix of :func:`write_atomic`'s temporary files (named ``.<file name>.<random>.tmp``).
_TEMP_SUFFIX = ".tmp"


def _temp_prefix(path: Path) -> str:
    return f".{path.name}."


def write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temp file in the same folder, fsync, rename, fsync
    of the folder); the file is created with mode 0600. A writer killed midway leaves ``path``
    as it was and at most a temporary file (see :func:`remove_stale_temporaries`)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=_temp_prefix(path), suffix=_TEMP_SUFFIX)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    folder = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(folder)
    finally:
        os.close(folder)


def stale_temporaries(path: Path) -> list[Path]:
    """Temporary files of :func:`write_atomic` for ``path`` (left there by a killed writer)."""
    return sorted(path.parent.glob(f"{_temp_prefix(path)}*{_TEMP_SUFFIX}"))


def remove_stale_temporaries(path: Path) -> None:
    """Delete the temporary files a writer of ``path`` killed inside :func:`write_atomic` left behind
    (only the single writer of ``path`` may call this, before it writes)."""
    for tmp in stale_temporaries(path):
        tmp.unlink(missing_ok=True)


class ConfigStore:
    """The versioned configuration in memory and in ``path``; :meth:`commit` is the only writer."""

    def __init__(self, path: Path, snapshot: Snapshot, history_length: int) -> None:
        self.path = path
        self.snapshot = snapshot
        self._history_length = history_length

    @classmethod
    def open(cls, path: Path, startup: StackConfig) -> ConfigStore:
        """Load ``path`` (or start at version 0 from ``startup`` if it does not exist yet).

        The caller becomes the store's single writer: temporary files a killed predecessor left
        next to ``path`` are removed first.
        """
        limit = startup.api.history_length
        if path.parent.is_dir():
            remove_stale_temporaries(path)
        if not path.exists():
            return cls(path, Snapshot(0, startup, None, ()), limit)
        try:
            stored = StoreFile.model_validate_json(path.read_bytes())
        except OSError as exc:
            raise StoreError(f"cannot read the config store {path}: {exc.strerror}") from None
        except ValidationError as exc:
            raise StoreError(f"the config store {path} is not a valid store file: {exc}") from None
        local = startup.model_dump(mode="json", include=set(LOCAL_SECTIONS))
        try:
            conf = validate_config({**stored.config, **local}, origin=str(path))
        except ConfigError as exc:
            raise StoreError(str(exc)) from None
        history = tuple(stored.history[-limit:])
        return cls(path, Snapshot(stored.version, conf, stored.updated_at, history), limit)

    def published(self) -> tuple[int, dict[str, Any]]:
        """The current version and configuration as published on the bus (JSON, no secrets)."""
        snapshot = self.snapshot
        return snapshot.version, public_config(snapshot.config).model_dump(mode="json")

    def commit(self, new: StackConfig, who: str, client: str, action: str, min_version: int = 0) -> HistoryEntry | None:
        """Persist ``new`` as the next version (above ``min_version`` too) and make it current.

        Returns the history entry, or None if ``new`` changes nothing (no new version, no write).
        Raises :class:`StoreError` if the file cannot be written; the current snapshot then stays.
        """
        current = self.snapshot
        diff = config_diff(public_config(current.config).model_dump(mode="json"), public_config(new).model_dump(mode="json"))
        if not diff:
            return None
        now = datetime.now(timezone.utc)
        version = max(current.version, min_version) + 1
        entry = HistoryEntry(version=version, time=now, who=who, client=client, action=action, diff=diff)
        history = (*current.history, entry)[-self._history_length :]
        document = StoreFile(
            version=version, updated_at=now, config=public_config(new).model_dump(mode="json"), history=list(history)
        )
        try:
            write_atomic(self.path, document.model_dump_json(indent=1).encode())
        except OSError as exc:
            raise StoreError(f"cannot write the config store {self.path}: {exc.strerror}") from None
        self.snapshot = Snapshot(version, new, now, history)
        return entry


def default_store_path(robot_id: str, environ: Mapping[str, str]) -> Path:
    """``$XDG_STATE_HOME/safemimic/<robot_id>/config.json`` (XDG_STATE_HOME: ~/.local/state)."""
    state = environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(state).expanduser() / "safemimic" / robot_id / "config.json"

