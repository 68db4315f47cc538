"""The TLS part of a Zenoh session's configuration, with the certificate files checked first.

:func:`tls_files` resolves ``bus.tls`` (:class:`~shared.config.TlsConfig`) for one identity and
checks, before Zenoh sees them, that the files exist and are readable, that the certificate and the
CA parse, that the certificate is valid now and was issued by that CA: a :class:`ConfigError` says
which file and what to run (``safemimic certs ...``), where Zenoh itself would only fail to open.
:func:`zenoh_tls` is the ``transport/link/tls`` block: mutual TLS (``enable_mtls``), the router
listening with its certificate, every session connecting with its own.
"""

from __future__ import annotations

import datetime
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cryptography import x509
from cryptography.exceptions import InvalidSignature

from shared.config import ConfigError, TlsConfig

ACL_FILE = "access_control.json5"


@dataclass(frozen=True)
class TlsFiles:
    """The resolved files of one session: CA, certificate, key, and (router) access control."""

    identity: str
    ca: Path
    certificate: Path
    private_key: Path
    access_control: Path | None


def _path(value: str | None, directory: str | None, default_name: str) -> Path:
    if value is not None:
        return Path(value).expanduser().resolve()
    assert directory is not None  # TlsConfig guarantees dir when a file is not named
    return (Path(directory).expanduser() / default_name).resolve()


def _readable(path: Path, what: str, hint: str) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"bus.tls: {what} {path} does not exist ({hint})") from None
    except OSError as exc:
        raise ConfigError(f"bus.tls: cannot read {what} {path}: {exc.strerror}") from None


def _certificate(data: bytes, path: Path, what: str) -> x509.Certificate:
    try:
        return x509.load_pem_x509_certificate(data)
    except ValueError as exc:
        raise ConfigError(f"bus.tls: {what} {path} is not a PEM certificate: {exc}") from None


def tls_files(tls: TlsConfig, identity: str, router: bool = False) -> TlsFiles:
    """The checked files of ``identity`` (``tls.identity`` wins); :class:`ConfigError` if unusable."""
    name = tls.identity or identity
    if not name:
        raise ConfigError("bus.tls: no identity: set bus.tls.identity (the certificate's name)")
    files = TlsFiles(
        identity=name,
        ca=_path(tls.ca, tls.dir, "ca.pem"),
        certificate=_path(tls.certificate, tls.dir, f"{name}.pem"),
        private_key=_path(tls.private_key, tls.dir, f"{name}.key"),
        access_control=_path(tls.access_control, tls.dir, ACL_FILE) if router else None,
    )
    where = tls.dir or files.certificate.parent
    ca = _certificate(_readable(files.ca, "CA certificate", f"`safemimic certs init {where}` makes one"),
                      files.ca, "CA certificate")
    hint = f"`safemimic certs issue {name} --dir {where}` makes it"
    cert = _certificate(_readable(files.certificate, f"certificate of {name!r}", hint), files.certificate,
                        f"certificate of {name!r}")
    _readable(files.private_key, f"private key of {name!r}", hint)
    now = datetime.datetime.now(datetime.timezone.utc)
    if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
        raise ConfigError(f"bus.tls: {files.certificate} is not valid now (valid {cert.not_valid_before_utc:%Y-%m-%d} "
                          f"to {cert.not_valid_after_utc:%Y-%m-%d}): issue a new one ({hint})")
    try:
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature):
        raise ConfigError(f"bus.tls: {files.certificate} was not issued by the CA {files.ca} (the router "
                          f"would refuse it): {hint}") from None
    if router and files.access_control is not None:
        _readable(files.access_control, "access-control file",
                  "a secure router needs its rules: `safemimic certs stack DIR` writes them from the service table")
    return files


def zenoh_tls(files: TlsFiles, router: bool) -> dict[str, Any]:
    """The ``transport/link/tls`` block: mutual TLS with this session's certificate."""
    block: dict[str, Any] = {
        "root_ca_certificate": str(files.ca),
        "enable_mtls": True,
        "connect_private_key": str(files.private_key),
        "connect_certificate": str(files.certificate),
    }
    if router:
        block["listen_private_key"] = str(files.private_key)
        block["listen_certificate"] = str(files.certificate)
    return block
