"""Shared fixtures: the real-data folder (skipped cleanly when absent) and small tolerances."""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import pytest  # noqa: E402

from rigbuild.paths import data_dir, ict_dir  # noqa: E402


#: test modules that share the session-scoped ``e2e_run`` (one build of the end-to-end session)
E2E_MODULES = ("tests/test_workflow_e2e.py", "tests/test_cluster_slurm.py")


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """pytest-xdist (``make test`` runs ``-n 2``): every test is its own unit of work, load-balanced, except the
    e2e and SLURM modules, which go to one worker together so that ``e2e_run`` is built once. (xdist's own
    ``--dist loadgroup`` marks do nothing under pytest 9.2: it renames ``item._nodeid``, which pytest no longer
    reads.) Another ``--dist`` given on the command line is left to xdist."""
    if config.getoption("dist", "load") != "load":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class E2EGroupScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return "e2e" if nodeid.split("::")[0].endswith(E2E_MODULES) else nodeid

    return E2EGroupScheduling(config, log)


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
