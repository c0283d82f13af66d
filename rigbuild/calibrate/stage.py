"""Runner of rule ``calibrate``: a session folder -> ``results/<session>/calib/`` (see
:mod:`rigbuild.calibrate.session` for the files). Never reads ground truth: rule ``eval_calibration``
(rules/eval_calibrate.smk) scores ``cameras.json`` against it.
"""

from __future__ import annotations

import os
from typing import Any, Mapping

from rigbuild.calibrate.params import from_config


def run_calibrate(session_dir: str | os.PathLike, out_dir: str | os.PathLike,
                  params: Mapping[str, Any] | None) -> dict[str, Any]:
    """Calibrate a session and write every output into ``out_dir`` (``calib_metrics.json`` is the fragment
    ``{"calibration": {...}}``).

    params : the raw ``config["params"]["calibrate"]`` block (checked by :func:`from_config`).
    Returns the ``calibration`` metrics.
    """
    from rigbuild.calibrate.session import calibrate_session, write_outputs

    spec, result = calibrate_session(session_dir, from_config(params))
    return write_outputs(result, out_dir, spec.name)
