"""Well-known locations: the real-data folder and the project root."""

from __future__ import annotations

import os
from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parent.parent


def data_dir() -> Path:
    """Folder with the real third-party test data.

    ``$RIGBUILD_DATA`` if set, else ``../shared/data`` relative to the project root. The folder may not
    exist; callers (tests) skip when it is absent.
    """
    env = os.environ.get("RIGBUILD_DATA")
    if env:
        return Path(env).expanduser().resolve()
    return (PROJECT_ROOT / ".." / "shared" / "data").resolve()


def ict_dir() -> Path:
    """The ICT-FaceKit ``FaceXModel`` folder inside :func:`data_dir`."""
    return data_dir() / "ict-facekit" / "FaceXModel"
