"""The bearer token that every write needs: ``$SAFEMIMIC_API_TOKEN``, else ``api.token``, else a
token generated at first start and kept (mode 0600) in a file next to the store."""

from __future__ import annotations

import os
import secrets
import stat
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from services.config_api.errors import ConfigApiError
from services.config_api.store import write_atomic

TOKEN_ENV = "SAFEMIMIC_API_TOKEN"
TOKEN_FILE_NAME = "api_token"
#: Shortest token accepted from the environment or a file (the generated one has 43 characters).
MIN_TOKEN_LENGTH = 16


class TokenError(ConfigApiError, RuntimeError):
    """The configured or stored token is unusable (the message says where it came from)."""


@dataclass(frozen=True)
class Token:
    """The token, where it came from, and whether this start generated it."""

    value: str
    origin: str
    generated: bool = False


def token_path(store: Path) -> Path:
    """Where a generated token is kept: ``api_token`` in the store's folder."""
    return store.parent / TOKEN_FILE_NAME


def resolve_token(configured: str | None, store: Path, environ: Mapping[str, str]) -> Token:
    """The write token: environment, then configuration, then the token file (created if missing)."""
    from_env = environ.get(TOKEN_ENV, "").strip()
    if from_env:
        if len(from_env) < MIN_TOKEN_LENGTH:
            raise TokenError(f"${TOKEN_ENV} must be at least {MIN_TOKEN_LENGTH} characters long")
        return Token(from_env, f"${TOKEN_ENV}")
    if configured:
        return Token(configured, "api.token")
    path = token_path(store)
    if path.exists():
        try:
            value = path.read_text().strip()
            if stat.S_IMODE(path.stat().st_mode) & 0o077:  # readable by others: tighten, as ssh would insist
                os.chmod(path, 0o600)
        except (OSError, UnicodeDecodeError) as exc:
            raise TokenError(f"cannot read the token file {path}: {exc}") from None
        if len(value) < MIN_TOKEN_LENGTH:
            raise TokenError(f"the token file {path} holds no token of at least {MIN_TOKEN_LENGTH} characters")
        return Token(value, str(path))
    value = secrets.token_urlsafe(32)
    try:
        write_atomic(path, (value + "\n").encode())
    except OSError as exc:
        raise TokenError(f"cannot write the token file {path}: {exc.strerror}") from None
    return Token(value, str(path), generated=True)
