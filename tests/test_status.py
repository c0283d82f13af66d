"""README's status table and docs/status.md are generated from the committed benchmarks/out/*.json."""

from __future__ import annotations

import importlib.util

from rigbuild.paths import PROJECT_ROOT


def test_status_pages_are_up_to_date_with_the_committed_benchmarks():
    spec = importlib.util.spec_from_file_location("status", PROJECT_ROOT / "benchmarks" / "status.py")
    status = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(status)
    assert status.main(["--check"]) == 0, "run: python benchmarks/status.py"
