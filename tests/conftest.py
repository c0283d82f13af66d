"""Shared fixtures: the real-data folder (skipped cleanly when absent) and small tolerances."""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import pytest  # noqa: E402

from rigbuild.paths import data_dir, ict_dir  # noqa: E402


@pytest.fixture(scope="session")
def real_data():
    """``$RIGBUILD_DATA`` (default ../shared/data); skips the test when the folder is absent."""
    d = data_dir()
    if not d.is_dir():
        pytest.skip(f"real data folder {d} is absent (set RIGBUILD_DATA to the shared data folder)")
    return d


@pytest.fixture(scope="session")
def ict_folder():
    """The ICT FaceXModel folder; skips when absent."""
    d = ict_dir()
    if not (d / "generic_neutral_mesh.obj").exists():
        pytest.skip(f"ICT-FaceKit not found at {d} (set RIGBUILD_DATA to the shared data folder)")
    return d


@pytest.fixture(scope="session")
def ict_rig(ict_folder):
    """The ICT template rig in mm (read once per test session)."""
    from rigbuild.io.rigs import read_ict_rig

    return read_ict_rig(ict_folder)


@pytest.fixture(scope="session")
def e2e_run(tmp_path_factory):
    """The end-to-end session's one run (tests/e2e_run.py), shared by the e2e and SLURM tests."""
    from e2e_run import run_e2e

    return run_e2e(tmp_path_factory)
