"""Rendered views of a textured head for the landmark level: cameras on a sphere around the face, realistic
shading (studio lights, GGX skin), one call per view. Used to build the landmark tables from the template
(:mod:`rigbuild.track.landmark_table`) and by the landmark tests on the real James scan.

World frame as everywhere: mm, +y up, the face looks towards +z, +x is the actor's left.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rigbuild.camera import Camera, look_at


def sphere_cameras(centre: np.ndarray, azimuths_deg, elevations_deg, distance_mm: float = 800.0,
                   width: int = 1280, height: int = 960, focal_px: float = 2400.0) -> list[Camera]:
    """Pinhole cameras looking at ``centre`` (3,) mm from ``distance_mm``; one per (azimuth, elevation) pair
    (degrees; azimuth about +y from +z towards +x, elevation towards +y). Principal point at the image centre."""
    cams = []
    K = np.array([[focal_px, 0, width / 2 - 0.5], [0, focal_px, height / 2 - 0.5], [0, 0, 1]])
    for i, (az, el) in enumerate(zip(np.radians(azimuths_deg), np.radians(elevations_deg))):
        d = np.array([np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)])
        R, t = look_at(np.asarray(centre, float) + distance_mm * d, np.asarray(centre, float), up=(0.0, 1.0, 0.0))
        cams.append(Camera(f"v{i:02d}", width, height, K, np.zeros(5), R, t))
    return cams


@dataclass
class HeadModel:
    """A textured head ready to render: ``mesh`` a :class:`rigbuild.render.TexturedMesh`, ``material`` a
    :class:`rigbuild.render.Material` (None: uniform skin), ``centre`` (3,) the face centre mm."""

    mesh: object
    material: object
    centre: np.ndarray


def template_head(rig, vertices: np.ndarray | None = None, size: int = 2048, seed: int = 0) -> HeadModel:
    """The rig (ICT) with the realistic painted skin of :func:`rigbuild.render.skin.skin_albedo`, at
    ``vertices`` (default the neutral); transparent eye overlays dropped."""
    from rigbuild.render import Material, TexturedMesh
    from rigbuild.render.skin import skin_albedo

    app = skin_albedo(rig, size, seed=seed)
    keep = app.visible_faces
    V = rig.neutral if vertices is None else vertices
    mesh = TexturedMesh(V, rig.faces[keep], app.uvs, app.face_uvs[keep], app.texture)
    centre = V[rig.landmarks[rig.landmarks >= 0]].mean(0)
    return HeadModel(mesh, Material(specular_map=app.specular, roughness_map=app.roughness), centre)


def james_frame(landmarks68: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, c): the rotation taking a scan to the face frame (+x from landmark 36 to 45, the actor's left; +y from
    the chin 8 to the eyes) and the face centre c (mean of the 68 points). Face frame = (X - c) @ R.T."""
    L = np.asarray(landmarks68, float)
    x = L[45] - L[36]
    x /= np.linalg.norm(x)
    y = (L[36] + L[45]) / 2 - L[8]
    y -= x * (x @ y)
    y /= np.linalg.norm(y)
    return np.stack([x, y, np.cross(x, y)]), L.mean(0)


#: iBUG 68 order of the LJSON groups (menpo names the sides as seen in the image: its "left" eye is the
#: subject's right, iBUG 36-41)
_IBUG_GROUPS = (("chin", 17), ("leyebrow", 5), ("reyebrow", 5), ("nose", 9), ("leye", 6), ("reye", 6), ("mouth", 20))


def james_landmarks68(ljson: dict, source) -> np.ndarray:
    """(68, 3) the LJSON's labelled points in iBUG 68 order (its groups are stored chin, leye, reye, leyebrow,
    nose, reyebrow, mouth)."""
    from rigbuild.errors import InputError

    g = ljson["groups"]["LJSON"]
    P = np.asarray(g["landmarks"]["points"], float)
    masks = {lab["label"]: lab["mask"] for lab in g["labels"]}
    if any(len(masks.get(name, ())) != n for name, n in _IBUG_GROUPS):
        raise InputError("james.ljson: expected the 68-point groups " + str(dict(_IBUG_GROUPS)), path=source)
    return P[np.concatenate([masks[name] for name, _ in _IBUG_GROUPS])]


def james_head(folder) -> tuple[HeadModel, np.ndarray]:
    """The real James scan (menpo3d-james-head: james.obj, .jpg, .ljson) in the face frame, face centre at the
    origin; returns the head and its 68 labelled landmarks (68, 3) in the same frame (the scan's units, mm)."""
    import json
    from pathlib import Path

    import cv2

    from rigbuild.errors import InputError
    from rigbuild.io.obj import read_obj
    from rigbuild.render import TexturedMesh

    folder = Path(folder)
    m = read_obj(folder / "james.obj")
    tex = cv2.imread(str(folder / "james.jpg"), cv2.IMREAD_COLOR)
    if tex is None:
        raise InputError("cannot read james.jpg", path=folder)
    L = james_landmarks68(json.loads((folder / "james.ljson").read_text()), folder / "james.ljson")
    R, c = james_frame(L)
    V = (m.vertices - c) @ R.T
    mesh = TexturedMesh(V, m.faces, m.uvs, m.face_uvs, np.ascontiguousarray(tex[..., ::-1]))
    return HeadModel(mesh, None, np.zeros(3)), (L - c) @ R.T


def render_views(head: HeadModel, cameras: list[Camera], seed: int = 0, with_geometry: bool = False) -> list:
    """(H, W, 3) uint8 sRGB images of ``head`` through each camera under the studio lights (key, fill, rim,
    soft shadows, GGX specular), with 1 level of 8-bit noise; ``with_geometry``: the whole
    :class:`rigbuild.render.RenderResult` per view instead (``tri_id`` / ``bary`` index ``head.mesh.faces``)."""
    from rigbuild.render import Material, default_studio_lights, render_mesh

    lights = default_studio_lights(head.centre, cameras)
    material = head.material or Material()
    out = [render_mesh(cam, head.mesh, lights=lights, material=material, noise_sigma=1.0, seed=seed + i,
                       with_geometry=with_geometry, background=(60, 60, 60)) for i, cam in enumerate(cameras)]
    return out if with_geometry else [r.color for r in out]
