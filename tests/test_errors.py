"""One error root: every exception class safemimic defines derives from SafemimicError, and each
package's errors from that package's own base."""

from __future__ import annotations

import importlib
import inspect
import os
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import safemimic
import services
import shared
from safemimic.certs import CertError
from services.config_api.errors import ConfigApiError
from services.executor.errors import ExecutorError, ExecutorStartError
from services.perception.errors import PerceptionError
from services.safety.errors import SafetyConfigError, SafetyError
from services.viewer.errors import ViewerError
from shared.errors import SafemimicError

#: package prefix → the base its errors derive from
PACKAGE_BASES = {
    "services.safety": SafetyError, "services.executor": ExecutorError, "services.perception": PerceptionError,
    "services.config_api": ConfigApiError, "services.viewer": ViewerError,
}


def _modules() -> list[str]:
    names = []
    for package in (shared, services, safemimic):
        for info in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
            if not info.name.endswith("__main__"):  # an entry point runs its service when imported
                names.append(info.name)
    return names


def _own_exceptions() -> list[type[BaseException]]:
    found = []
    for name in _modules():
        module = importlib.import_module(name)
        for _, obj in inspect.getmembers(module, inspect.isclass):
            if issubclass(obj, BaseException) and obj.__module__ == name:
                found.append(obj)
    return found


def test_every_exception_we_define_derives_from_the_root_and_its_package_base() -> None:
    exceptions = _own_exceptions()
    assert len(exceptions) >= 20  # the walk found them (codec's five, config, spec, services', ...)
    for exc in exceptions:
        assert issubclass(exc, SafemimicError), f"{exc.__module__}.{exc.__qualname__} does not derive from SafemimicError"
        base = next((b for prefix, b in PACKAGE_BASES.items() if exc.__module__.startswith(prefix + ".")), None)
        if base is not None:
            assert issubclass(exc, base), f"{exc.__module__}.{exc.__qualname__} does not derive from {base.__name__}"


def test_start_up_refusals_of_both_executor_backends_share_a_base() -> None:
    from services.executor.g1.errors import G1StartError
    from services.executor.mujoco.model import SimModelError

    assert issubclass(G1StartError, ExecutorStartError) and issubclass(SimModelError, ExecutorStartError)
    assert issubclass(CertError, SafemimicError)


def test_safety_domain_errors_are_its_own_type() -> None:
    from services.safety.pairs import make_pair_set, preset_pair_set
    from services.safety.qp import make_backend

    with pytest.raises(SafetyConfigError, match="unknown pair preset"):
        preset_pair_set("nonsense", [])
    with pytest.raises(SafetyConfigError, match="two different robot capsules"):
        make_pair_set([("torso", "torso")])
    with pytest.raises(SafetyConfigError, match="unknown QP backend"):
        make_backend("nonsense")


# every command: a refusal is one clear message and exit 2, never a traceback ----------------------
def _safemimic(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "safemimic.cli", *argv], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "SAFEMIMIC_API_TOKEN": "t" * 32}, cwd=Path(__file__).resolve().parent.parent)


@pytest.mark.parametrize("command", ["safety", "perception", "executor", "router", "config-api", "health"])
def test_an_endpoint_without_its_protocol_is_a_configuration_error_in_every_command(command: str) -> None:
    done = _safemimic(command, "--insecure", "--connect" if command != "router" else "--listen", "192.168.1.10:7447")
    assert done.returncode == 2, done
    assert "Traceback" not in done.stderr, done.stderr
    assert "'192.168.1.10:7447' is not a Zenoh endpoint" in done.stderr and "tcp/10.0.0.2:7447" in done.stderr
    assert "(from the command line)" in done.stderr, done.stderr


@pytest.mark.parametrize("command", ["safety", "perception"])
def test_a_missing_certificate_stops_a_service_with_one_line(command: str, tmp_path: Path) -> None:
    """The certificate is read when the bus opens, inside the service: the entry point says it."""
    done = _safemimic(command, "--certs", str(tmp_path / "nowhere"), "--mode", "client", "--connect",
                      "tls/127.0.0.1:7447", "--duration", "1")
    assert done.returncode == 2, done
    assert "Traceback" not in done.stderr, done.stderr
    assert f"safemimic {command}: bus.tls: CA certificate" in done.stderr and "does not exist" in done.stderr
