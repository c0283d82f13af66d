"""How a synthetic camera sees a frame: appearance, lights, sensor (the ``synthetic:`` block's realism keys).

:func:`capture_setup` builds, once per session, what every image shares: the face's albedo (the painted
``speckle`` or the ``realistic`` skin of :mod:`rigbuild.render.skin`) and its specular maps, the lights
(``single``: one Lambert light, or ``studio``: key, fill and rim with soft shadows and GGX specular) and the
sensor (``camera``: :class:`rigbuild.render.sensor.SensorParams`, or None for 8-bit Gaussian noise).
:func:`capture_face` and :func:`capture_board` render one image with it. With every realism key at its
default the images are today's, bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from rigbuild.errors import InputError
from rigbuild.params import did_you_mean

APPEARANCES = ("speckle", "realistic")
LIGHTINGS = ("single", "studio")
DOTS = ("stencil", "none")


@dataclass
class CaptureSetup:
    """What every image of a session shares.

    texture : (S, S, 3) uint8 albedo; uvs (T, 2), face_uvs (F', 3) its texture coordinates; faces (F', 3) the
    rendered triangles (ICT's transparent eye overlays dropped with the realistic skin); material : a
    :class:`rigbuild.render.lights.Material` or None; lights : list of Light or None (the single Lambert light);
    sensor : SensorParams or None; shutter : exposure as a fraction of the frame interval; noise_sigma : the
    8-bit noise without a sensor; msaa : anti-aliasing; seed : the session seed (per-camera sensor offsets).
    """

    texture: np.ndarray
    uvs: np.ndarray
    face_uvs: np.ndarray
    faces: np.ndarray
    material: Any
    lights: list | None
    sensor: Any
    shutter: float
    noise_sigma: float
    msaa: bool
    seed: int = 0

    @property
    def linear(self) -> bool:
        return self.sensor is not None

    def sensor_for(self, camera):
        """This camera's sensor: the session's, with the camera's own exposure and white-balance offsets."""
        from rigbuild.render.sensor import camera_sensor

        return camera_sensor(self.sensor, camera.id, self.seed)


def check_capture_keys(p: Mapping[str, Any], where: str) -> None:
    """Fail at DAG start on a bad realism key of a ``synthetic:`` block (``where``: ``sessions.<s>.synthetic``)."""
    from rigbuild.render.sensor import SensorParams

    for key, allowed in (("appearance", APPEARANCES), ("lights", LIGHTINGS), ("dots", DOTS)):
        if p[key] not in allowed:
            raise InputError(f"field '{where}.{key}' is {p[key]!r}{did_you_mean(p[key], allowed)}", path="config",
                             fix=f"use one of: {', '.join(allowed)}")
    for key in ("dot_placement_sd_mm", "dot_missing_fraction", "noise_sigma"):
        if float(p[key]) < 0:
            raise InputError(f"field '{where}.{key}' is {p[key]}: a standard deviation or fraction cannot be negative",
                             path="config", fix=f"give {key} >= 0 (0 = none)")
    if not 0 <= float(p["dot_missing_fraction"]) < 1:
        raise InputError(f"field '{where}.dot_missing_fraction' is {p['dot_missing_fraction']}", path="config",
                         fix="give a fraction in [0, 1)")
    lo, hi = (float(x) for x in p["dot_diameter_mm"])
    if not 0 < lo <= hi:
        raise InputError(f"field '{where}.dot_diameter_mm' is {p['dot_diameter_mm']}", path="config",
                         fix="give [lo, hi] with 0 < lo <= hi (mm)")
    lo, hi = (float(x) for x in p["dot_darkness"])
    if not 0 <= lo <= hi <= 1:
        raise InputError(f"field '{where}.dot_darkness' is {p['dot_darkness']}", path="config",
                         fix="give [lo, hi] with 0 <= lo <= hi <= 1 (fraction of light the paint absorbs)")
    if not 0 <= float(p["shutter"]) <= 1:
        raise InputError(f"field '{where}.shutter' is {p['shutter']}", path="config",
                         fix="give the exposure as a fraction of the frame interval, in [0, 1]")
    try:
        SensorParams.from_dict(p["camera"]) if p["camera"] is not None else None
    except InputError as exc:
        raise InputError(f"{where}: {exc}", path="config") from None


def capture_setup(p: Mapping[str, Any], actor, cameras: Sequence, face_centre: np.ndarray, width: int) -> CaptureSetup:
    """The session's shared capture state from the synthetic block ``p`` (defaults filled in)."""
    from rigbuild.render.mesh import speckle_texture

    seed = int(p["seed"])
    size = 2048 if width >= 1000 else 1024
    material = None
    if p["appearance"] == "realistic":
        from rigbuild.render.lights import Material
        from rigbuild.render.skin import skin_albedo

        app = skin_albedo(actor, size, seed=seed)
        keep = app.visible_faces
        texture, uvs, face_uvs, faces = app.texture, app.uvs, app.face_uvs[keep], actor.faces[keep]
        material = Material(specular_map=app.specular, roughness_map=app.roughness)
    else:
        texture, uvs, face_uvs, faces = speckle_texture(size, seed=seed), actor.uvs, actor.face_uvs, actor.faces
    lights = None
    if p["lights"] == "studio":
        from rigbuild.render.lights import Material, default_studio_lights

        lights = default_studio_lights(face_centre, cameras)
        material = material or Material()
    sensor = None
    if p["camera"] is not None:
        from rigbuild.render.sensor import SensorParams

        sensor = SensorParams.from_dict(p["camera"])
    return CaptureSetup(texture, uvs, face_uvs, faces, material, lights, sensor, float(p["shutter"]),
                        float(p["noise_sigma"]), bool(p["msaa"]), seed)


def exposure_motion(verts: np.ndarray, i: int, shutter: float) -> np.ndarray:
    """(V, 3) mm: how far each vertex of frame ``i`` of ``verts`` (F, V, 3) moves while the shutter is open
    (``shutter`` of the frame interval), from the central difference of the neighbouring frames."""
    lo, hi = max(i - 1, 0), min(i + 1, verts.shape[0] - 1)
    if hi == lo:
        return np.zeros_like(verts[i])
    return (verts[hi] - verts[lo]) * (float(shutter) / (hi - lo))


def capture_face(camera, setup: CaptureSetup, vertices: np.ndarray, seed: int, motion: np.ndarray | None = None,
                 dot_centers: np.ndarray | None = None, dot_radius_mm=1.5, dot_albedo=(25, 25, 25)) -> np.ndarray:
    """One ROM image (H, W, 3) uint8 of the face ``vertices`` (V, 3) mm; ``motion`` (V, 3) mm over the
    exposure (motion blur, with a sensor); painted dots at ``dot_centers`` (D, 3) with per-dot radius/albedo."""
    return render_face(camera, setup, vertices, seed, motion, dot_centers, dot_radius_mm, dot_albedo)()


def render_face(camera, setup: CaptureSetup, vertices: np.ndarray, seed: int, motion: np.ndarray | None = None,
                dot_centers: np.ndarray | None = None, dot_radius_mm=1.5,
                dot_albedo=(25, 25, 25)) -> Callable[[], np.ndarray]:
    """:func:`capture_face` in two steps: renders now (GL, this thread) and returns ``finish() -> (H, W, 3)
    uint8``, the sensor (numpy and OpenCV only: it may run on another thread while the next image renders)."""
    from rigbuild.render import render_mesh
    from rigbuild.render.common import noise_rng
    from rigbuild.render.mesh import TexturedMesh

    blur = setup.linear and motion is not None and setup.sensor.motion_blur_samples > 1 and setup.shutter > 0
    mesh = TexturedMesh(vertices, setup.faces, setup.uvs, setup.face_uvs, setup.texture, dot_centers=dot_centers,
                        dot_radius_mm=dot_radius_mm, dot_albedo=dot_albedo, vertex_motion=motion if blur else None)
    if not setup.linear:
        color = render_mesh(camera, mesh, lights=setup.lights, material=setup.material, noise_sigma=setup.noise_sigma,
                            msaa=setup.msaa, seed=seed, with_geometry=False).color
        return lambda: color
    from rigbuild.render.sensor import apply_sensor

    res = render_mesh(camera, mesh, lights=setup.lights, material=setup.material, output="linear", msaa=setup.msaa,
                      seed=seed, with_geometry=setup.sensor.f_number is not None, with_motion=blur)
    return lambda: apply_sensor(res.linear, camera, setup.sensor_for(camera), noise_rng(camera, seed),
                                depth_mm=res.depth, motion_px=res.motion_px if blur else None)


def capture_board(camera, setup: CaptureSetup, board, R_board: np.ndarray, t_board: np.ndarray, seed: int) -> np.ndarray:
    """One calibration image (H, W, 3) uint8 of the board at pose (R_board, t_board), through the sensor."""
    return render_board_capture(camera, setup, board, R_board, t_board, seed)()


def render_board_capture(camera, setup: CaptureSetup, board, R_board: np.ndarray, t_board: np.ndarray,
                         seed: int) -> Callable[[], np.ndarray]:
    """:func:`capture_board` in two steps: renders now (GL) and returns ``finish() -> (H, W, 3) uint8`` (the
    sensor, no GL: it may run on another thread)."""
    from rigbuild.render.board import render_board

    if not setup.linear:
        img = render_board(camera, board, R_board, t_board, noise_sigma=setup.noise_sigma, msaa=setup.msaa, seed=seed)
        return lambda: img
    import dataclasses

    from rigbuild.render.common import noise_rng
    from rigbuild.render.sensor import apply_sensor

    linear = render_board(camera, board, R_board, t_board, msaa=setup.msaa, seed=seed, output="linear")
    still = dataclasses.replace(setup.sensor_for(camera), f_number=None)  # boards: rendered without depth, so in focus
    return lambda: apply_sensor(linear, camera, still, noise_rng(camera, seed))