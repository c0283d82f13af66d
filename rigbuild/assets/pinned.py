"""Files the project fetches once from a package registry and pins by sha256 (the face models, three.js).

One pattern for every such asset: a folder under ``<sys.prefix>/share/rigbuild/<kind>`` (an environment
variable overrides it), members of a downloaded archive checked against pinned digests and written atomically,
and an idempotent install that returns at once when every file is present with its digest.
"""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path
from typing import Callable, Mapping

from rigbuild.errors import InputError

#: file name -> (member of the downloaded archive, sha256 of the member)
PinnedFiles = Mapping[str, tuple[str, str]]


def asset_dir(env_var: str, kind: str) -> Path:
    """``$<env_var>`` or ``<sys.prefix>/share/rigbuild/<kind>``."""
    env = os.environ.get(env_var)
    return Path(env) if env else Path(sys.prefix) / "share" / "rigbuild" / kind


def sha256_file(path: Path) -> str:
    """Hex sha256 of a file's bytes."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def files_present(folder: Path, files: PinnedFiles) -> bool:
    """True when every file of ``files`` is in ``folder`` with its pinned digest."""
    return all((folder / n).is_file() and sha256_file(folder / n) == d for n, (_, d) in files.items())


def write_members(read_member: Callable[[str], bytes], files: PinnedFiles, folder: Path, archive: Path,
                  install_command: str) -> None:
    """Write each pinned member of ``archive`` (``read_member(member) -> bytes``) into ``folder`` after its sha256
    check (InputError naming the archive otherwise), each file atomically."""
    folder.mkdir(parents=True, exist_ok=True)
    for name, (member, digest) in files.items():
        data = read_member(member)
        got = hashlib.sha256(data).hexdigest()
        if got != digest:
            raise InputError(f"{member} in {archive.name} has sha256 {got}, expected {digest}", path=archive,
                             fix=f"the download is corrupt or another version: run `{install_command}` again")
        tmp = folder / f".{name}.part"
        tmp.write_bytes(data)
        os.replace(tmp, folder / name)


def install(folder: Path, files: PinnedFiles, fetch: Callable[[Path], None], what: str, install_command: str) -> Path:
    """Idempotent install: nothing when ``folder`` holds every file; else ``fetch(folder)`` (download and
    :func:`write_members`) and a final check. Returns the folder."""
    if files_present(folder, files):
        return folder
    fetch(folder)
    if not files_present(folder, files):
        raise InputError(f"{what} failed their sha256 check after install", path=folder,
                         fix=f"delete the folder and run `{install_command}`")
    return folder


def main(argv: list[str] | None, prog: str, description: str, default_dir: Callable[[], Path],
         run_install: Callable[[str | None, str | None], Path], archive_flag: str, archive_help: str) -> int:
    """The ``install`` / ``path`` command line of an asset module."""
    import argparse

    ap = argparse.ArgumentParser(prog=prog, description=description)
    ap.add_argument("command", choices=["install", "path"])
    ap.add_argument("--dir", default=None, help="target folder (default: the venv's share/rigbuild folder)")
    ap.add_argument(archive_flag, dest="archive", default=None, help=archive_help)
    a = ap.parse_args(argv)
    if a.command == "path":
        print(Path(a.dir) if a.dir else default_dir())
        return 0
    print(run_install(a.dir, a.archive))
    return 0
