"""The personalized rig's files, in the conventions they state.

The fit runs in the calibrated cameras' world (the first camera's OpenCV frame: y down, the face 0.5 m away);
``weights.npz`` and ``fit.npz`` stay there (the ground-truth evaluation maps them with the cameras). The rig
files are moved into the template's head frame (:data:`rigbuild.rig.HEAD_FRAME_AXES`: +y up, +z towards the
viewer, the origin at the template head's centre; glTF in metres) by the rigid capture-to-head transform of
the personalized neutral onto the template (:func:`rigbuild.rig.head_frame_transform`), which is saved beside
them as ``head_frame.json`` (and as ``capture_to_head`` (4, 4) in the rig npz files):

- head frame: ``rig.npz``, ``initial_rig.npz``, ``rig_obj/`` (``rig.json``), ``rig.gltf``
- capture frame: ``weights.npz`` (per-frame rotation and translation), ``fit.npz``

With ``export: {names: arkit}`` the rig files carry ARKit's 52 names (:func:`rigbuild.io.arkit.arkit_rig`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from rigbuild.io.atomic import write_json
from rigbuild.io.gltf import write_gltf_rig
from rigbuild.io.rigs import write_obj_folder_rig, write_rig_npz
from rigbuild.personalize.params import ExportParams
from rigbuild.rig import HEAD_FRAME_AXES, Rig, head_frame_transform

log = logging.getLogger(__name__)

HEAD_FRAME_FILE = "head_frame.json"
HEAD_FRAME_FILES = ["rig.npz", "initial_rig.npz", "rig_obj/", "rig.gltf"]
CAPTURE_FRAME_FILES = ["weights.npz", "fit.npz"]


def capture_to_head_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The (4, 4) homogeneous matrix of ``x_head = R x_capture + t``."""
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, t
    return M


def head_frame_record(R: np.ndarray, t: np.ndarray, rms_mm: float, template: Rig) -> dict:
    """``head_frame.json``: the transform, its convention and which files are in which frame."""
    return {"capture_to_head": capture_to_head_matrix(R, t).tolist(),
            "convention": "x_head = M @ [x_capture, 1]; millimetres; M[:3, :3] a rotation (no scale)",
            "axes": HEAD_FRAME_AXES, "origin": f"the template rig's origin ('{template.name}': the head's centre)",
            "fit": {"vertices": "the template's face region", "n_vertices": int(template.face_vertices.size),
                    "rms_mm": rms_mm},
            "head_frame_files": HEAD_FRAME_FILES, "capture_frame_files": CAPTURE_FRAME_FILES}


def export_rigs(out: Path, rig: Rig, initial: Rig, template: Rig, params: ExportParams | None = None) -> dict:
    """Write ``rig.npz``, ``initial_rig.npz``, ``rig_obj/``, ``rig.gltf`` (``rig`` and ``initial`` in the capture
    frame, mm) in the template's head frame, and ``head_frame.json``. Returns the head-frame record (with the
    ARKit naming under ``naming`` when asked for)."""
    params = params or ExportParams()
    R, t, rms = head_frame_transform(template, rig.neutral)
    record = head_frame_record(R, t, rms, template)
    log.info("capture -> head frame: rotation %.1f deg, translation %s mm, face fit RMS %.2f mm",
             np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))), np.round(t, 1).tolist(), rms)
    head, head_initial = rig.transformed(R, t), initial.transformed(R, t)
    extras = {"frame": "template head frame (head_frame.json: capture_to_head)"}
    if params.names == "arkit":
        from rigbuild.io.arkit import arkit_rig

        head, naming = arkit_rig(head)
        head_initial, _ = arkit_rig(head_initial)
        record["naming"] = naming
        extras.update(naming)
        log.info("ARKit names: %d of 52 ARKit shapes written; ARKit shapes without a counterpart in the rig: %s; "
                    "rig shapes without an ARKit counterpart (kept under their own names): %s", len(naming["arkit_sources"]),
                    ", ".join(naming["arkit_missing"]) or "none", ", ".join(naming["no_arkit_counterpart"]) or "none")
    M = capture_to_head_matrix(R, t)
    write_rig_npz(out / "rig.npz", head, capture_to_head=M)
    write_rig_npz(out / "initial_rig.npz", head_initial, capture_to_head=M)
    write_obj_folder_rig(head, out / "rig_obj", extras)
    write_gltf_rig(out / "rig.gltf", head, extras=extras)
    write_json(out / HEAD_FRAME_FILE, record)
    return record
