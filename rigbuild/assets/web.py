"""The report's front-end library: three.js 0.149.0 (MIT), the last release with the UMD ``build/three.min.js``.

The session report (:mod:`rigbuild.report`) inlines ``three.min.js`` in a classic ``<script>`` so that the page's
3D rig viewer and take playback work offline from ``file://``. ``python -m rigbuild.assets.web install`` fetches
the package with ``npm pack three@0.149.0`` into a temporary folder (npm talks to the npm registry), checks the
sha256 of the tarball and of the two members pinned below, and writes them into ``<sys.prefix>/share/rigbuild/web``
(``$RIGBUILD_WEB`` overrides the folder). It is idempotent: when both files are present with the pinned digests
it returns at once. Same download-check-extract pattern as :mod:`rigbuild.assets.face_models`.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

from rigbuild.assets import pinned
from rigbuild.assets.pinned import asset_dir, sha256_file, write_members
from rigbuild.errors import InputError

THREE_VERSION = "0.149.0"
INSTALL_COMMAND = f"{Path(sys.executable).name} -m rigbuild.assets.web install"
#: sha256 of ``three-0.149.0.tgz`` as the npm registry serves it
TARBALL_SHA256 = "ab8b7c131f6ce72e05081dff4882046584e4a4ce5ad864f9f2a0e3146cc3997c"
#: file name -> (member of the npm tarball, sha256 of the member)
FILES = {
    "three.min.js": ("package/build/three.min.js",
                     "8a5f7249903b54d30f79f708699d2fed2d6a1d0741a4cd41377d1f01bb5a2271"),
    "three.LICENSE": ("package/LICENSE", "852e0e8699169bf9f6fdc6bda3e682d078dcbc738b5d33e74df594721bff271d"),
}


def web_dir() -> Path:
    """The folder holding the files: ``$RIGBUILD_WEB`` or ``<sys.prefix>/share/rigbuild/web``."""
    return asset_dir("RIGBUILD_WEB", "web")


def asset_path(name: str = "three.min.js") -> Path:
    """The installed file ``name`` (a key of :data:`FILES`); InputError with the install command if absent or
    not the pinned file."""
    if name not in FILES:
        raise InputError(f"unknown web asset {name!r}", fix=f"use one of: {', '.join(FILES)}")
    path = web_dir() / name
    if not path.is_file():
        raise InputError(f"three.js {THREE_VERSION} ({name}) is not installed: the report's 3D viewer needs it",
                         path=path, fix=f"run `{INSTALL_COMMAND}` (or `make setup`)")
    if sha256_file(path) != FILES[name][1]:
        raise InputError(f"{name} is not three.js {THREE_VERSION} (sha256 differs)", path=path,
                         fix=f"delete it and run `{INSTALL_COMMAND}`")
    return path


def _extract(tarball: Path, folder: Path) -> None:
    got = sha256_file(tarball)
    if got != TARBALL_SHA256:
        raise InputError(f"{tarball.name} has sha256 {got}, expected {TARBALL_SHA256}", path=tarball,
                         fix=f"the download is corrupt or not three@{THREE_VERSION}: run `{INSTALL_COMMAND}` again")
    with tarfile.open(tarball, "r:gz") as tar:
        def read(member: str) -> bytes:
            fh = tar.extractfile(member)
            return fh.read() if fh is not None else b""

        write_members(read, FILES, folder, tarball, INSTALL_COMMAND)


def _npm_pack(tmp: Path) -> Path:
    npm = shutil.which("npm")
    if npm is None:
        raise InputError("npm is not installed (needed once, to fetch three.js from the npm registry)",
                         fix=f"apt-get install npm, then run `{INSTALL_COMMAND}`; or pass --tarball "
                             f"three-{THREE_VERSION}.tgz downloaded elsewhere")
    r = subprocess.run([npm, "pack", f"three@{THREE_VERSION}", "--silent", "--pack-destination", str(tmp)],
                       capture_output=True, text=True, cwd=tmp)
    tarballs = sorted(tmp.glob("three-*.tgz"))
    if r.returncode != 0 or not tarballs:
        raise InputError(f"npm pack three@{THREE_VERSION} failed: {r.stderr.strip()[-400:]}",
                         fix=f"check the network / npm registry, then run `{INSTALL_COMMAND}` again")
    return tarballs[0]


def install(folder: str | os.PathLike | None = None, tarball: str | os.PathLike | None = None) -> Path:
    """Install the files into ``folder`` (default :func:`web_dir`); return the folder.

    tarball: an already downloaded ``three-0.149.0.tgz`` (otherwise ``npm pack`` fetches it). Nothing is
    downloaded when the files are already present with the pinned digests."""
    folder = Path(folder) if folder is not None else web_dir()

    def fetch(f: Path) -> None:
        if tarball is not None:
            return _extract(Path(tarball), f)
        with tempfile.TemporaryDirectory() as tmp:
            _extract(_npm_pack(Path(tmp)), f)

    return pinned.install(folder, FILES, fetch, "three.js", INSTALL_COMMAND)


def main(argv: list[str] | None = None) -> int:
    return pinned.main(argv, "python -m rigbuild.assets.web", __doc__.split("\n")[0], web_dir, install, "--tarball",
                       f"use this downloaded three-{THREE_VERSION}.tgz instead of npm")


if __name__ == "__main__":
    sys.exit(main())
