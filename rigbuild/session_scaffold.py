"""``rigbuild init-session``: build ``session.yaml`` from a folder laid out as the session contract says,
then check the folder against it (every camera has calibration images, every ROM frame has every view,
all images share one size and decode) and check the board description on a few calibration images of
each camera (:func:`check_board`), so a wrong board spec is caught before a run."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from rigbuild.errors import InputError
from rigbuild.session import IMAGE_SUFFIXES, SessionSpec, read_session, write_session

_FRAME = re.compile(r"^(\d+)\.png$")


def _image_size(path: Path) -> tuple[int, int] | None:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    return None if img is None else (int(img.shape[1]), int(img.shape[0]))


def scan_session_folder(folder: Path) -> dict[str, Any]:
    """Infer cameras, image size, ROM sequences and performances from the folder layout."""
    calib = folder / "calib"
    if not calib.is_dir():
        raise InputError("no calib/ folder", path=folder, fix="put board images in calib/<camera>/<n>.png")
    cameras = sorted(d.name for d in calib.iterdir() if d.is_dir())
    if len(cameras) < 2:
        raise InputError(f"found {len(cameras)} camera folders under calib/ (need 2 or more)", path=calib)
    first = next((p for cam in cameras for p in sorted((calib / cam).iterdir())
                  if p.suffix.lower() in IMAGE_SUFFIXES), None)
    if first is None:
        raise InputError("no PNG/JPEG images under calib/<camera>/", path=calib)
    size = _image_size(first)
    if size is None:
        raise InputError("cannot decode image", path=first, fix="re-export the image as PNG")
    rom = []
    rom_dir = folder / "rom"
    for seq in sorted(d for d in rom_dir.iterdir() if d.is_dir()) if rom_dir.is_dir() else []:
        frames = sorted({int(m.group(1)) for cam in seq.iterdir() if cam.is_dir()
                         for p in cam.iterdir() if (m := _FRAME.match(p.name))})
        if frames:
            rom.append({"name": seq.name, "frames": [frames[0], frames[-1]], "neutral_frame": frames[0]})
    perfs = [{"name": p.stem, "file": f"performances/{p.name}"}
             for p in sorted((folder / "performances").glob("*")) if p.suffix.lower() in (".c3d", ".npz")]
    return {"name": re.sub(r"[^A-Za-z0-9_.-]", "_", folder.resolve().name), "units": "mm", "cameras": cameras,
            "image_size": list(size), "rom": rom, "performances": perfs}


def check_session_folder(spec: SessionSpec) -> list[str]:
    """Problems with the files of a session (missing views, unreadable or mis-sized images)."""
    problems = []
    for cam in spec.cameras:
        imgs = spec.calib_images(cam)
        if not imgs:
            problems.append(f"camera {cam}: no calibration images in {spec.calib_dir(cam)}")
        for p in imgs:
            size = _image_size(p)
            if size is None:
                problems.append(f"{p}: cannot decode image")
            elif size != (spec.width, spec.height):
                problems.append(f"{p}: size {size[0]}x{size[1]}, session says {spec.width}x{spec.height}")
    for seq in spec.rom:
        for f in seq.frames:
            for cam in spec.cameras:
                if not spec.rom_image(seq.name, cam, f).exists():
                    problems.append(f"{spec.rom_image(seq.name, cam, f)}: missing view")
    for perf in spec.performances:
        if not (spec.root / perf.file).exists():
            problems.append(f"{spec.root / perf.file}: performance file missing")
    return problems


def check_board(spec: SessionSpec, per_camera: int = 3) -> tuple[list[str], list[str]]:
    """Detect the board in the first ``per_camera`` calibration images of every camera.

    Returns (report lines: corners found per image and camera, problems: cameras where the board was found in
    none of them, with what was tried and which nearby board description finds corners)."""
    from rigbuild.calibrate.detect import describe_board, detect_board, diagnose_board, read_gray

    n_all = len(spec.board.corner_points()[1])
    lines, problems, missing = [f"board check ({describe_board(spec.board)}; {n_all} corners):"], [], {}
    for cam in spec.cameras:
        paths = spec.calib_images(cam)[:per_camera]
        grays = {p.name: read_gray(p) for p in paths}
        found = [len(detect_board(g, spec.board)) for g in grays.values()]
        lines.append(f"  {cam}: " + (", ".join(f"{n}/{n_all}" for n in found) + f" corners in {len(found)} images"
                                     if found else "no calibration images"))
        if paths and not any(found):
            missing[cam] = grays
    if missing:
        cam, grays = next(iter(missing.items()))
        problems.append(f"board not found in the sample images of {', '.join(missing)}; "
                        + "; ".join(diagnose_board(grays, spec.board)))
    return lines, problems


def scaffold_session(folder: Path, board: dict, fps: float = 60.0, template_rig: str = "procedural",
                     force: bool = False) -> tuple[SessionSpec, list[str]]:
    """Write ``folder/session.yaml`` (unless it exists and not ``force``), read it back, check the files."""
    folder = Path(folder)
    if force or not (folder / "session.yaml").exists():
        data = scan_session_folder(folder)
        data.update(fps=fps, board=board, template_rig=template_rig)
        write_session(data, folder)
    spec = read_session(folder)
    return spec, check_session_folder(spec)
