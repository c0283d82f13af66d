"""Runner of rule ``calibrate``: a session folder -> ``results/<session>/calib/`` (see
:mod:`rigbuild.calibrate.session` for the files). Never reads ground truth: rule ``eval_calibration``
(rules/eval_calibrate.smk) scores ``cameras.json`` against it.

Quality gate (RMS per camera, bundle convergence): every output is written first (status ``fail`` in
``calib_metrics.json``, residual CSVs and plot included), then, with ``params.calibrate.gate: fail``, the
job fails. Snakemake deletes a failed job's outputs, so they are also copied to
``results/<session>/calib_diagnostics/``. ``gate: warn`` logs the failure and goes on.
"""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path
from typing import Any, Mapping

from rigbuild.calibrate.params import from_config
from rigbuild.errors import QualityGateError


def run_calibrate(session_dir: str | os.PathLike, out_dir: str | os.PathLike,
                  params: Mapping[str, Any] | None, workers: int = 1) -> dict[str, Any]:
    """Calibrate a session and write every output into ``out_dir`` (``calib_metrics.json`` is the fragment
    ``{"calibration": {...}}``).

    params : the raw ``config["params"]["calibrate"]`` block (checked by :func:`from_config`).
    workers : threads for the board detection (the rule's threads).
    Returns the ``calibration`` metrics; raises QualityGateError after writing when the gate fails
    (``gate: fail``).
    """
    from rigbuild.calibrate.detect import session_images
    from rigbuild.calibrate.session import calibrate_session, output_files, write_outputs

    opt = from_config(params)
    spec, result = calibrate_session(session_dir, opt, workers)
    metrics = write_outputs(result, out_dir, spec.name, session_images(spec))
    if not result.gate_failures:
        return metrics
    out_dir = Path(out_dir)
    keep = out_dir.parent / f"{out_dir.name}_diagnostics"
    shutil.rmtree(keep, ignore_errors=True)
    for rel in output_files(result):
        (keep / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(out_dir / rel, keep / rel)
    text = "\n".join(result.gate_failures) + f"\n  every output was written (status fail); a copy is in {keep}"
    if opt.gate == "warn":
        logging.warning("%s\n  params.calibrate.gate: warn, going on", text)
        return metrics
    raise QualityGateError(text + "\n  (params.calibrate.gate: warn keeps the pipeline going)")
