"""``safemimic config-api``: serve the config API and web console with uvicorn (architecture §1).

On start: load the configuration (file, environment, flags), then the store (the persisted
configuration wins over the file, except this process's robot id, bus and API settings), resolve
the write token, publish the current configuration, serve until SIGINT/SIGTERM. Prints one JSON
line ``{"event": "ready", "url": ..., "version": ..., "store": ...}`` once it accepts requests.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import uvicorn

from services.config_api.app import create_app
from services.config_api.dependencies import ApiContext
from services.config_api.link import SERVICE_NAME, BusLink
from services.config_api.store import ConfigStore, default_store_path
from services.config_api.token import resolve_token
from services.config_api.writer import ConfigWriter
from shared.bus import Bus
from shared.cli_args import add_bus_arguments, config_from_args
from shared.config import StackConfig
from shared.robot_spec import configured_robot_spec

log = logging.getLogger("safemimic.config_api")
#: Open event streams get this long to finish when the server stops (s).
_GRACEFUL_SHUTDOWN_S = 1


def store_location(conf: StackConfig, environ: Mapping[str, str]) -> Path:
    """``api.store``, else the default state file of this robot."""
    return Path(conf.api.store).expanduser() if conf.api.store else default_store_path(conf.robot_id, environ)


def _announce_when_ready(server: uvicorn.Server, store: ConfigStore) -> None:
    """Print the ready line once uvicorn listens (the port is known then, also for ``--port 0``)."""
    while not server.started:
        if server.should_exit:
            return
        time.sleep(0.01)
    host, port = server.servers[0].sockets[0].getsockname()[:2]
    host = f"[{host}]" if ":" in host else host  # IPv6 literal
    ready = {"event": "ready", "url": f"http://{host}:{port}", "version": store.snapshot.version, "store": str(store.path)}
    print(json.dumps(ready), flush=True)


def main(conf: StackConfig, environ: Mapping[str, str] = os.environ) -> None:
    """Serve the API for ``conf`` until SIGINT/SIGTERM. Raises StoreError / TokenError on a bad store or token."""
    store = ConfigStore.open(store_location(conf, environ), conf)
    token = resolve_token(conf.api.token, store.path, environ)
    if token.generated:
        print(f"config-api: generated the API token (kept in {token.origin}, mode 0600): {token.value}", flush=True)
    with Bus(conf.bus, conf.robot_id, SERVICE_NAME) as bus:
        link = BusLink(bus, store.published)
        writer = ConfigWriter(store, link, conf.api.ack_timeout_s, configured_robot_spec(store.snapshot.config))
        context = ApiContext(settings=conf.api, store=store, link=link, writer=writer, token=token.value)
        version, config = store.published()
        link.publish(version, [], config)
        server = uvicorn.Server(
            uvicorn.Config(
                create_app(context), host=conf.api.host, port=conf.api.port, access_log=False,
                timeout_graceful_shutdown=_GRACEFUL_SHUTDOWN_S, log_config=None,
            )
        )
        log.info("config v%d from %s; writes need the token from %s", store.snapshot.version, store.path, token.origin)
        threading.Thread(target=_announce_when_ready, args=(server, store), daemon=True).start()
        server.run()


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic config-api")
    parser.description = (
        "Serve the config API (REST + web console at /): the single writer of the stack's parameters. "
        "Accepted changes are persisted, published on Zenoh as ConfigUpdate and acknowledged by the "
        "safety service. Writes need the bearer token ($SAFEMIMIC_API_TOKEN, api.token, or generated "
        "at first start and printed once)."
    )
    add_bus_arguments(parser)
    group = parser.add_argument_group("HTTP server")
    group.add_argument("--host", help="address to bind (default api.host: 127.0.0.1, loopback only)")
    group.add_argument("--port", type=int, help="TCP port (default api.port: 8080; 0: any free port)")
    group.add_argument("--store", metavar="FILE", help="where accepted changes persist (default api.store, else $XDG_STATE_HOME/safemimic/<robot_id>/config.json)")
    return parser


def run(args: argparse.Namespace) -> int:
    api: dict[str, Any] = {key: value for key in ("host", "port", "store") if (value := getattr(args, key)) is not None}
    # a ConfigError, StoreError or TokenError is shared.entrypoint's to say, exit 2
    main(config_from_args(args, {"api": api} if api else None))
    return 0

