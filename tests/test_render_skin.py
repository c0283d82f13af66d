"""Tests of the realistic skin appearance (rigbuild.render.skin): contrast against the real James scan,
region colours and roughness, determinism, speed."""

from __future__ import annotations

import time

import numpy as np
import pytest

from rigbuild.render import skin
from rigbuild.render.skin import JAMES_CONTRAST, REGION_CODES, SkinParams, skin_albedo, skin_contrast

S = 2048


@pytest.fixture(scope="module")
def proc_rig():
    from rigbuild.assets.head import procedural_head_rig

    return procedural_head_rig()


@pytest.fixture(scope="module")
def ict_small(ict_folder):
    from rigbuild.io.rigs import read_ict_rig

    return read_ict_rig(ict_folder, expressions=[])


@pytest.fixture(scope="module")
def ict_app(ict_small):
    t0 = time.perf_counter()
    app = skin_albedo(ict_small, S, seed=0)
    print(f"ICT skin atlas {S}^2: {time.perf_counter() - t0:.2f} s")
    return app


def _contrast(app, rig):
    sk = np.isin(app.face_regions, [REGION_CODES["skin"], REGION_CODES["head"]])
    return skin_contrast(app.texture, rig.neutral, rig.faces, app.uvs, app.face_uvs, rig.neutral[rig.landmarks], sk)


def _mean_lum(app, mask):
    return float(skin.luminance(app.texture)[mask].mean())


def test_rasterize_uv_exact():
    # two triangles covering the unit square: every texel covered once, barycentrics reproduce the centre
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    fu = np.array([[0, 1, 2], [0, 2, 3]])
    tri, bary = skin.rasterize_uv(uv, fu, (16, 24))
    assert (tri >= 0).all()
    assert np.allclose(bary.sum(-1), 1, atol=1e-6)
    r, c = np.mgrid[0:16, 0:24]
    u, v = (c + 0.5) / 24, 1 - (r + 0.5) / 16
    P = uv[fu[tri]]
    rec = (bary[..., None] * P).sum(-2)
    assert np.allclose(rec[..., 0], u, atol=1e-5) and np.allclose(rec[..., 1], v, atol=1e-5)


@pytest.mark.parametrize("which", ["procedural", "ict"])
def test_contrast_matches_james(which, request):
    rig = request.getfixturevalue("proc_rig" if which == "procedural" else "ict_small")
    app = skin_albedo(rig, S, seed=0)
    c = _contrast(app, rig)
    for w, ref in JAMES_CONTRAST.items():
        assert abs(c[w] / ref - 1) < 0.25, (w, c[w], ref)


def test_james_constant(real_data):
    folder = real_data / "menpo3d-james-head"
    if not (folder / "james.jpg").exists():
        pytest.skip("menpo3d-james-head is absent")
    c = skin.james_skin_contrast(folder)
    for w, ref in JAMES_CONTRAST.items():
        assert abs(c[w] - ref) < 0.002, (w, c[w], ref)


def test_lips_redder_and_smoother_than_cheeks(proc_rig):
    app = skin_albedo(proc_rig, 1024, seed=1)
    L = proc_rig.neutral[proc_rig.landmarks]
    tri, bary = skin.rasterize_uv(app.uvs, app.face_uvs, (1024, 1024))
    cov = tri >= 0
    pts = skin.texel_points(tri, bary, proc_rig.neutral, proc_rig.faces, cov)
    lip_c = L[[51, 57]].mean(0)  # middle of the lips
    cheek_c = L[[2, 31, 41]].mean(0)
    near = lambda c, r: np.linalg.norm(pts - proc_rig.neutral[np.argmin(((proc_rig.neutral - c) ** 2).sum(1))], axis=1) < r  # noqa: E731
    lip = np.zeros(cov.shape, bool)
    lip[cov] = near(lip_c, 3.0)
    cheek = np.zeros(cov.shape, bool)
    cheek[cov] = near(cheek_c, 8.0)
    tex = app.texture.astype(float)
    redness = lambda m: tex[m][:, 0].mean() / tex[m][:, 1:].mean()  # noqa: E731
    assert redness(lip) > 1.15 * redness(cheek)
    assert app.roughness[lip].mean() < app.roughness[cheek].mean() - 0.1


def test_ict_regions(ict_app, ict_small):
    app = ict_app
    reg = app.regions
    skin_m = reg == REGION_CODES["skin"]
    lum = skin.luminance(app.texture)
    # mouth interior darker than skin
    assert lum[reg == REGION_CODES["mouth_socket"]].mean() < 0.5 * lum[skin_m].mean()
    # pupil < iris < sclera, and a smooth cornea; by distance from the eye axis on the left eye
    tri, bary = skin.rasterize_uv(app.uvs, app.face_uvs, app.texture.shape[:2])
    eye = (reg == REGION_CODES["sclera"]) | (reg == REGION_CODES["iris"])
    pts = skin.texel_points(tri, bary, ict_small.neutral, ict_small.faces, eye)
    X = ict_small.neutral
    c = skin._sphere_fit(X[21451:22221])
    ic = X[22221:23021].mean(0)
    a = (ic - c) / np.linalg.norm(ic - c)
    rel = pts - c
    front = rel @ a > 0
    r = np.linalg.norm(rel - np.outer(rel @ a, a), axis=1)
    left = np.linalg.norm(pts - c, axis=1) < 20
    le = lum[eye]
    pupil, iris, sclera = le[left & front & (r < 1.2)], le[left & front & (r > 3) & (r < 5)], le[left & (r > 9)]
    assert pupil.mean() < 0.5 * iris.mean() and iris.mean() < 0.5 * sclera.mean()
    rough = app.roughness[eye]
    assert rough[left & front & (r < 5)].mean() < 0.5 * app.roughness[skin_m].mean()
    # teeth brighter than the gums; the overlays are flagged hidden
    assert lum[reg == REGION_CODES["teeth"]].mean() > lum[reg == REGION_CODES["gums"]].mean()
    assert not app.visible_faces[app.face_regions == REGION_CODES["eye_occlusion"]].any()
    assert app.visible_faces[app.face_regions == REGION_CODES["skin"]].all()


def test_deterministic_and_cached(proc_rig):
    a = skin_albedo(proc_rig, 512, seed=3)
    assert skin_albedo(proc_rig, 512, seed=3) is a
    skin._CACHE.clear()
    b = skin_albedo(proc_rig, 512, seed=3)
    assert np.array_equal(a.texture, b.texture) and np.array_equal(a.roughness, b.roughness)
    c = skin_albedo(proc_rig, 512, seed=4)
    assert not np.array_equal(a.texture, c.texture)
    assert a.texture.shape == (512, 512, 3) and a.texture.dtype == np.uint8
    assert a.roughness.shape == (512, 512) and a.specular.dtype == np.float32
    assert a.uvs.shape == (3 * len(proc_rig.faces), 2) and a.uvs.min() >= 0 and a.uvs.max() <= 1


def test_speckle_untouched():
    from rigbuild.render.mesh import speckle_texture

    t = speckle_texture(64, seed=0)
    assert t.shape == (64, 64, 3)


def test_bad_params():
    from rigbuild.errors import InputError

    with pytest.raises(InputError):
        SkinParams(stubble=-1)


def test_speed_ict(ict_small):
    skin._CACHE.clear()
    t0 = time.perf_counter()
    skin_albedo(ict_small, S, seed=7)
    dt = time.perf_counter() - t0
    print(f"ICT {S}^2 paint: {dt:.2f} s")
    assert dt < 30.0  # generous for a shared 2-core machine
