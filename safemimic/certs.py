"""``safemimic certs``: the deployment's own certificate authority and one certificate per identity.

Contracts:

- ``safemimic certs init DIR`` writes ``DIR/ca.pem`` (a self-signed CA certificate) and
  ``DIR/ca.key`` (its private key, mode 0600); it refuses to replace an existing CA without
  ``--force`` (every certificate it signed would stop being accepted).
- ``safemimic certs issue NAME --dir DIR`` writes ``DIR/NAME.pem`` and ``DIR/NAME.key`` (0600): a
  certificate with common name NAME signed by ``DIR/ca.pem``/``ca.key``. The router's access control
  (:mod:`safemimic.acl`) knows a session by that common name. ``--host`` adds subject alternative
  names (DNS names or IP addresses): the router's certificate must name every address clients
  connect to (``tls/HOST:PORT``: clients check the name, as browsers do).
- ``safemimic certs stack DIR`` makes everything one deployment needs at once: the CA if there is
  none, a certificate for each identity of the service table that has none yet, and the router's
  access-control rules ``DIR/access_control.json5``. ``--split`` also copies each identity's own
  three files (``ca.pem``, ``NAME.pem``, ``NAME.key``) into ``DIR/NAME/``, the folder a container
  of that service mounts (never the CA key, never another service's key).

Keys are ECDSA P-256 (rustls, Zenoh's TLS, accepts them); certificates carry both server and
client authentication usages, so one certificate serves a router (listening) and a client.
Everything is made by the ``cryptography`` library; nothing here is hand-rolled.
"""

from __future__ import annotations

import argparse
import datetime
import ipaddress
import os
import re
import shutil
import sys
from collections.abc import Sequence
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from shared.errors import SafemimicError

CA_CERT = "ca.pem"
CA_KEY = "ca.key"
CA_DAYS = 3650
CERT_DAYS = 825
#: A name usable as certificate common name, file name and ACL subject.
NAME_PATTERN = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]{0,63}$")


class CertError(SafemimicError, ValueError):
    """A certificate cannot be made as asked (missing CA, existing files, bad name); the message says why."""


def _now() -> datetime.datetime:
    return datetime.datetime.now(datetime.timezone.utc)


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey) -> None:
    """The private key as unencrypted PKCS#8 PEM, readable by its owner only."""
    data = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as out:
        out.write(data)
    os.chmod(path, 0o600)


def _write_cert(path: Path, cert: x509.Certificate) -> None:
    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def check_name(name: str) -> str:
    """``name`` if it can be a common name and a file name, else :class:`CertError`."""
    if not NAME_PATTERN.match(name) or name in ("ca", "access_control"):
        raise CertError(f"bad identity name {name!r}: letters, digits, '_', '.', '-' (not 'ca')")
    return name


def init_ca(directory: str | Path, force: bool = False, days: int = CA_DAYS) -> tuple[Path, Path]:
    """Create the CA in ``directory`` (created if missing): ``(ca.pem, ca.key)``."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    cert_path, key_path = directory / CA_CERT, directory / CA_KEY
    if not force and (cert_path.exists() or key_path.exists()):
        raise CertError(f"{cert_path} already exists: every certificate it signed would stop working "
                        "(use --force to replace it anyway)")
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "safemimic deployment CA")])
    now = _now()
    cert = (
        x509.CertificateBuilder()
        .subject_name(name).issuer_name(name).public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5)).not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                     content_commitment=False, key_encipherment=False, data_encipherment=False,
                                     key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    _write_key(key_path, key)
    _write_cert(cert_path, cert)
    return cert_path, key_path


def _load_ca(directory: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    cert_path, key_path = directory / CA_CERT, directory / CA_KEY
    if not cert_path.exists() or not key_path.exists():
        raise CertError(f"no CA in {directory} ({CA_CERT} and {CA_KEY}): run `safemimic certs init {directory}` first")
    try:
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    except ValueError as exc:
        raise CertError(f"cannot read the CA in {directory}: {exc}") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise CertError(f"{key_path} is not an EC key")
    return cert, key


def _san(name: str, hosts: Sequence[str]) -> list[x509.GeneralName]:
    names: list[x509.GeneralName] = []
    for host in (name, *hosts):
        try:
            entry: x509.GeneralName = x509.IPAddress(ipaddress.ip_address(host))
        except ValueError:
            entry = x509.DNSName(host)
        if entry not in names:
            names.append(entry)
    return names


def issue(name: str, directory: str | Path, hosts: Sequence[str] = (), days: int = CERT_DAYS,
          force: bool = True) -> tuple[Path, Path]:
    """Issue ``directory/NAME.pem`` + ``NAME.key`` with common name ``name``, signed by the CA there.

    ``hosts`` become subject alternative names besides ``name`` itself (IP addresses or DNS names).
    With ``force=False`` an existing pair is kept and returned unchanged.
    """
    directory = Path(directory)
    check_name(name)
    cert_path, key_path = directory / f"{name}.pem", directory / f"{name}.key"
    if not force and cert_path.exists() and key_path.exists():
        return cert_path, key_path
    ca_cert, ca_key = _load_ca(directory)
    key = ec.generate_private_key(ec.SECP256R1())
    now = _now()
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
        .issuer_name(ca_cert.subject).public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5)).not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=False, crl_sign=False,
                                     content_commitment=False, key_encipherment=False, data_encipherment=False,
                                     key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                       critical=False)
        .add_extension(x509.SubjectAlternativeName(_san(name, hosts)), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    _write_key(key_path, key)
    _write_cert(cert_path, cert)
    return cert_path, key_path


def split(name: str, directory: str | Path, owner: tuple[int, int] | None = None) -> Path:
    """Copy ``ca.pem``, ``NAME.pem`` and ``NAME.key`` into ``directory/NAME/`` (what that service mounts)."""
    directory = Path(directory)
    own = directory / name
    own.mkdir(exist_ok=True)
    for file in (CA_CERT, f"{name}.pem", f"{name}.key"):
        shutil.copy2(directory / file, own / file)
    os.chmod(own / f"{name}.key", 0o600)
    if owner is not None:
        for path in (own, *own.iterdir()):
            os.chown(path, *owner)
    return own


def make_stack(directory: str | Path, router_hosts: Sequence[str] = (), do_split: bool = False,
               owner: tuple[int, int] | None = None) -> list[str]:
    """The CA (if missing), every identity's certificate (if missing) and ``access_control.json5``.

    The router's certificate names ``router_hosts`` too. Returns the identities. Idempotent: running
    it again keeps existing keys (a one-shot container may start twice).
    """
    from safemimic.acl import ACL_FILE, ROUTER_IDENTITY, acl_text, identities

    directory = Path(directory)
    if not (directory / CA_CERT).exists():
        init_ca(directory)
    names = [ROUTER_IDENTITY, *(identity.name for identity in identities())]
    for name in names:
        issue(name, directory, hosts=router_hosts if name == ROUTER_IDENTITY else (), force=False)
        if do_split:
            split(name, directory, owner)
    (directory / ACL_FILE).write_text(acl_text())
    if do_split:
        shutil.copy2(directory / ACL_FILE, directory / ROUTER_IDENTITY / ACL_FILE)
        if owner is not None:
            os.chown(directory / ROUTER_IDENTITY / ACL_FILE, *owner)
    return names


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic certs")
    parser.description = ("The deployment's certificate authority and one certificate per service: the Zenoh "
                          "router accepts only sessions with a certificate of this CA, and its access control "
                          "knows each by its common name.")
    sub = parser.add_subparsers(dest="action", required=True)
    init = sub.add_parser("init", help="create the CA: DIR/ca.pem and DIR/ca.key")
    init.add_argument("dir", type=Path, metavar="DIR")
    init.add_argument("--force", action="store_true", help="replace an existing CA")
    issue_p = sub.add_parser("issue", help="issue DIR/NAME.pem and DIR/NAME.key (common name NAME), signed by DIR's CA")
    issue_p.add_argument("name", metavar="NAME", help="identity: router, executor, safety, perception, config_api, demo, health, viewer")
    issue_p.add_argument("--dir", type=Path, required=True, metavar="DIR", help="folder holding ca.pem and ca.key")
    issue_p.add_argument("--host", action="append", default=[], metavar="HOST",
                         help="also valid for this DNS name or IP address (the router: every address clients connect to)")
    issue_p.add_argument("--days", type=int, default=CERT_DAYS, help=f"validity (default {CERT_DAYS})")
    stack = sub.add_parser("stack", help="CA + every identity's certificate + the router's access_control.json5 (missing ones only)")
    stack.add_argument("dir", type=Path, metavar="DIR")
    stack.add_argument("--host", action="append", default=[], metavar="HOST", help="an address of the router (repeatable)")
    stack.add_argument("--split", action="store_true", help="also DIR/NAME/{ca.pem,NAME.pem,NAME.key} per identity")
    stack.add_argument("--owner", metavar="UID:GID", help="with --split: owner of each identity's folder")
    sub.metavar = "{" + ",".join(sub.choices) + "}"  # a missing action: "required: {init,issue,stack}"
    return parser


def run(args: argparse.Namespace) -> int:
    try:
        if args.action == "init":
            for path in init_ca(args.dir, force=args.force):
                print(f"wrote {path}")
        elif args.action == "issue":
            for path in issue(args.name, args.dir, hosts=args.host, days=args.days):
                print(f"wrote {path}")
        else:
            owner = None
            if args.owner:
                uid, _, gid = args.owner.partition(":")
                owner = (int(uid), int(gid or uid))
            names = make_stack(args.dir, router_hosts=args.host, do_split=args.split, owner=owner)
            print(f"certs: {args.dir} ({', '.join(names)})")
    except (CertError, OSError) as exc:
        print(f"safemimic certs: {exc}", file=sys.stderr)
        return 2
    return 0
