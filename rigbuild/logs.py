"""Logging for Snakemake entry points: every rule logs to its ``log:`` file."""

from __future__ import annotations

import contextlib
import logging
import sys
import time
import traceback
from pathlib import Path
from typing import Any, Callable

from rigbuild.determinism import setup_job
from rigbuild.progress import LOGGER as PROGRESS_LOGGER


def job_label(snakemake: Any) -> str:
    """``"track_sequence session=demo seq=rom01"``: the rule and its wildcards, to prefix a job's progress lines."""
    wildcards = getattr(snakemake, "wildcards", None)
    items = dict(wildcards.items()) if hasattr(wildcards, "items") else {}
    return " ".join([str(getattr(snakemake, "rule", "?"))] + [f"{k}={v}" for k, v in items.items()])


def run_logged(snakemake: Any, main: Callable[[Any], None]) -> None:
    """Run ``main(snakemake)`` with stdout/stderr, logging and warnings going to the rule's log.

    On an exception the traceback is written to the log and the error's message is printed to the
    real stderr (so the user sees 'file: what is wrong / fix: ...' in the Snakemake output), then the
    process exits non-zero. Progress lines (:mod:`rigbuild.progress`) also go to the real stderr, prefixed with
    :func:`job_label`, so that a long job is not silent in Snakemake's output. Before ``main`` runs,
    :func:`rigbuild.determinism.setup_job` sizes OpenCV's thread pool to the job's ``threads`` and seeds the
    global random generators (two runs of a job on the same inputs give the same outputs).
    """
    pinned = setup_job(int(getattr(snakemake, "threads", 1) or 1))
    log_path = Path(snakemake.log[0]) if len(snakemake.log) else None
    if log_path is None:
        main(snakemake)
        return
    log_path.parent.mkdir(parents=True, exist_ok=True)
    real_stderr = sys.stderr
    with open(log_path, "w", buffering=1) as fh, contextlib.redirect_stdout(fh), contextlib.redirect_stderr(fh):
        handler = logging.StreamHandler(fh)
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        logger = logging.getLogger()  # every logger (rigbuild.*, libraries, warnings) goes to the log
        logger.addHandler(handler)
        logger.setLevel(logging.INFO)
        logging.captureWarnings(True)
        shown = logging.StreamHandler(real_stderr)
        shown.setFormatter(logging.Formatter(f"[{job_label(snakemake)}] %(message)s"))
        progress_logger = logging.getLogger(PROGRESS_LOGGER)
        progress_logger.addHandler(shown)
        logging.getLogger(__name__).info("reproducibility: %s", pinned)
        t0 = time.perf_counter()
        try:
            main(snakemake)
        except Exception as exc:
            traceback.print_exc(file=fh)
            print(f"\nrigbuild error in rule {getattr(snakemake, 'rule', '?')}: {exc}\n  (log: {log_path})",
                  file=real_stderr)
            raise SystemExit(1) from None
        finally:
            logger.removeHandler(handler)
            progress_logger.removeHandler(shown)
            print(f"elapsed {time.perf_counter() - t0:.2f} s", file=fh)
