"""The Zenoh router's access control, generated from the service table (:mod:`safemimic.stack`).

One source of truth: every identity's :class:`~safemimic.stack.BusRights` (the four services of
:data:`~safemimic.stack.SERVICES` and the observing tools of :data:`~safemimic.stack.TOOLS`)
becomes Zenoh's ``access_control`` block with ``default_permission: deny``. A subject is a
certificate common name (``cert_common_names``, mutual TLS: :mod:`shared.tls`); its rules allow,
per message kind and direction (``ingress``: from that session into the router; ``egress``: from
the router to it), on key expressions ``safemimic/*/<topic>`` (any robot id):

- a topic it ``puts``: ``put`` ingress, and ``declare_subscriber`` egress (it learns that someone
  listens, so its publisher sends: matching status);
- a topic it ``subscribes``: ``declare_subscriber`` ingress and ``put`` egress;
- its ``token``: ``liveliness_token`` ingress on ``alive/<identity>`` only;
- ``watches_alive``: ``declare_liveliness_subscriber`` and ``liveliness_query`` ingress and
  ``liveliness_token`` egress on ``alive/*``; ``queries_alive``: ``liveliness_query`` ingress and
  ``liveliness_token`` egress on ``alive/*``.

Everything else is dropped by the router: e.g. perception's ``put`` on ``config`` or
``robot/command`` never reaches the safety service or the executor; ``delete``, queryables,
queries and replies are allowed to nobody. The router identity has no rules (one router).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from safemimic.stack import SERVICES, TOOLS, BusRights
from shared.bus import KEY_PREFIX, TOPICS
from shared.tls import ACL_FILE

__all__ = ["ACL_FILE", "ROUTER_IDENTITY", "Identity", "access_control", "acl_text", "identities"]

#: The router's certificate name (``services.router.main.ROUTER_IDENTITY``).
ROUTER_IDENTITY = "router"
_HEADER = """\
// Zenoh access control of the safemimic router. GENERATED from the service table in
// safemimic/stack.py (SERVICES' and TOOLS' BusRights) by safemimic.acl: edit the table, not this.
"""


@dataclass(frozen=True)
class Identity:
    """A certificate common name and what its sessions may do."""

    name: str
    rights: BusRights


def identities() -> list[Identity]:
    """Every identity that gets a certificate besides the router: the services, then the tools."""
    return [Identity(spec.token, spec.rights) for spec in SERVICES] + [Identity(n, r) for n, r in TOOLS.items()]


def _key(topic: str) -> str:
    if topic not in TOPICS:
        raise ValueError(f"unknown topic {topic!r} in the service table; known: {', '.join(TOPICS)}")
    return f"{KEY_PREFIX}/*/{topic}"


def _rules(identity: Identity) -> list[dict[str, Any]]:
    rights, name = identity.rights, identity.name
    alive_all = f"{KEY_PREFIX}/*/alive/*"
    wanted: list[tuple[str, list[str], str, list[str]]] = []
    if rights.puts:
        keys = [_key(topic) for topic in rights.puts]
        wanted += [("put", ["put"], "ingress", keys), ("put matching", ["declare_subscriber"], "egress", keys)]
    if rights.subscribes:
        keys = [_key(topic) for topic in rights.subscribes]
        wanted += [("subscribe", ["declare_subscriber"], "ingress", keys), ("receive", ["put"], "egress", keys)]
    if rights.token:
        wanted.append(("own token", ["liveliness_token"], "ingress", [f"{KEY_PREFIX}/*/alive/{name}"]))
    if rights.watches_alive or rights.queries_alive:
        asks = ["liveliness_query", *(["declare_liveliness_subscriber"] if rights.watches_alive else [])]
        wanted += [("ask tokens", asks, "ingress", [alive_all]), ("see tokens", ["liveliness_token"], "egress", [alive_all])]
    return [{"id": f"{name}: {what}", "permission": "allow", "flows": [flow], "messages": messages, "key_exprs": keys}
            for what, messages, flow, keys in wanted]


def access_control() -> dict[str, Any]:
    """Zenoh's ``access_control`` block for the whole table (default deny)."""
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for identity in identities():
        own = _rules(identity)
        rules += own
        subjects.append({"id": identity.name, "cert_common_names": [identity.name]})
        policies.append({"id": identity.name, "subjects": [identity.name], "rules": [rule["id"] for rule in own]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def acl_text() -> str:
    """The JSON5 file the router loads (``bus.tls.access_control``, ``DIR/access_control.json5``)."""
    return _HEADER + json.dumps(access_control(), indent=2) + "\n"
