"""The report's 3D view and its front-end library (rigbuild.report.viewer, rigbuild.assets.web), and the page in
headless Chromium: a tiny synthetic results folder written here (a rig, two characters, two takes, a picture),
the page's in-page self-check (a slider moves a vertex, a take frame moves the mesh, no console errors), a
screenshot at 1400x900 with the summary above the fold, and the page size."""

from __future__ import annotations

import base64
import json
import re
import shutil
import subprocess
import tarfile

import numpy as np
import pytest

from rigbuild.assets import web
from rigbuild.errors import InputError
from rigbuild.io.curves import write_weight_curves_csv
from rigbuild.io.rigs import write_rig_npz
from rigbuild.report.html import build_report
from rigbuild.report.viewer import DATA_JS, THREE_JS, Packer, pack_take, take_files, viewer_data
from rigbuild.rig import Rig

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def _decode(b64: str, dtype) -> np.ndarray:
    return np.frombuffer(base64.b64decode(b64), dtype=np.dtype(dtype).newbyteorder("<"))


def grid_rig(n: int = 12, name: str = "personalized", scale: float = 1.0) -> Rig:
    """An n x n vertex sheet 100 mm wide facing +z, three shapes: the lower half down (jawOpen, up to 10 mm),
    the corners out (mouthSmile, 4 mm), one vertex forward (bump, 2 mm)."""
    u, v = np.meshgrid(np.linspace(-50, 50, n), np.linspace(-50, 50, n))
    neutral = np.stack([u.ravel(), v.ravel(), 5 * np.cos(u.ravel() / 40) * np.cos(v.ravel() / 40)], 1) * scale
    q = np.arange(n * n).reshape(n, n)
    faces = np.concatenate([np.stack([q[:-1, :-1].ravel(), q[:-1, 1:].ravel(), q[1:, 1:].ravel()], 1),
                            np.stack([q[:-1, :-1].ravel(), q[1:, 1:].ravel(), q[1:, :-1].ravel()], 1)])
    d = np.zeros((3, n * n, 3))
    low = neutral[:, 1] < 0
    d[0, low, 1] = -10 * (-neutral[low, 1] / 50)
    d[1, :, 0] = 4 * np.sign(neutral[:, 0]) * (np.abs(neutral[:, 0]) > 40)
    d[2, n * n // 2 + n // 2, 2] = 2
    return Rig(neutral=neutral, deltas=d, shape_names=["jawOpen", "mouthSmile", "bump"], faces=faces, name=name,
               face_region=np.arange(n * n))


def tiny_results(root):
    """results/<s>/ with a personalized rig, characters template and stylized, a Ribera take on template and a
    Seol take on stylized, and a picture; returns (folder, rig, {take csv: (character rig, weights)})."""
    import cv2

    res = root / "results" / "tiny"
    rig = grid_rig()
    write_rig_npz(res / "personalize" / "rig.npz", rig)
    chars = {"template": grid_rig(name="template"), "stylized": grid_rig(name="stylized", scale=1.3)}
    for c, r in chars.items():
        write_rig_npz(res / "characters" / f"{c}.npz", r)
    t = np.arange(60) / 30.0
    takes = {}
    for method, c, peak in (("ribera", "template", 1.3), ("seol", "stylized", 0.7)):
        # one most active frame (30 * peak): jawOpen peaks there, mouthSmile holds after 1 s
        w = np.stack([np.exp(-(((t - peak) / 0.3) ** 2)), 0.3 * (t > 1), np.zeros_like(t)], 1)
        path = res / "retarget" / method / "perf00" / c / "weights.csv"
        path.parent.mkdir(parents=True)
        write_weight_curves_csv(path, w, chars[c].shape_names, 30.0)
        takes[path] = (chars[c], w)
    (res / "calib").mkdir()
    img = np.full((300, 900, 3), 255, np.uint8)
    cv2.circle(img, (450, 150), 100, (40, 90, 200), -1)
    cv2.imwrite(str(res / "calib" / "residuals.png"), img)
    return res, rig, takes


def test_packed_rig_and_takes_decode_to_the_rig_within_their_quantization(tmp_path):
    res, rig, takes = tiny_results(tmp_path)
    data = viewer_data(res)
    assert list(data["models"]) == ["m0", "m1", "m2"] and len(data["topologies"]) == 1  # one face list, shared
    m = data["models"]["m0"]
    assert m["shapes"] == rig.shape_names and m["n_vertices"] == rig.neutral.shape[0]
    q = _decode(m["neutral"]["q"], np.int16).reshape(-1, 3).astype(float)
    neutral = np.asarray(m["neutral"]["lo"]) + (q + 32767) * np.asarray(m["neutral"]["step"])
    assert np.abs(neutral - rig.neutral).max() <= 0.51 * max(m["neutral"]["step"])
    faces = _decode(data["topologies"][m["faces"]], np.uint16).reshape(-1, 3)
    assert np.array_equal(faces, rig.faces)
    idx, vals = _decode(m["idx"], np.uint16), _decode(m["deltas"], np.int16).reshape(-1, 3)
    at = 0
    for k, n in enumerate(m["counts"]):
        moved = np.flatnonzero(np.linalg.norm(rig.deltas[k], axis=1) > 0.01)
        assert np.array_equal(idx[at:at + n], moved)
        assert np.abs(vals[at:at + n] * m["scales"][k] - rig.deltas[k, moved]).max() <= 0.51 * m["scales"][k]
        at += n
    assert m["counts"] == [int((rig.neutral[:, 1] < 0).sum()), int((np.abs(rig.neutral[:, 0]) > 40).sum()), 1]
    order = [f[0] for f in take_files(res)]  # by performance, character, then the pipeline's method order
    assert order == [res / "retarget/seol/perf00/stylized/weights.csv", res / "retarget/ribera/perf00/template/weights.csv"]
    for csv, take in zip(order, data["takes"]):
        char, w = takes[csv]
        wq = _decode(take["weights"], np.int16).reshape(w.shape)
        assert np.abs(take["offset"] + wq * take["scale"] - w).max() <= 1e-5 + 0.51 * take["scale"]
        assert take["fps"] == pytest.approx(30.0, abs=1e-3) and take["n_frames"] == 60
        assert data["models"][take["model"]]["label"].startswith(f"character {char.name}")
    one = pack_take(sorted(takes)[0], "m1", "x")
    assert one["shapes"] == ["jawOpen", "mouthSmile", "bump"]


def test_a_large_rig_is_cut_to_its_face_region(tmp_path):
    rig = grid_rig(n=20)
    rig.face_region = np.flatnonzero(rig.neutral[:, 1] > 0)
    m = Packer(max_vertices=100).model(rig, "big")
    kept = m["n_vertices"]
    assert kept == rig.face_region.size and m["counts"][0] == 0  # jawOpen moves only the lower half, cut away


def test_the_library_installs_from_its_pinned_tarball_and_says_how_when_missing(tmp_path, monkeypatch):
    monkeypatch.setenv("RIGBUILD_WEB", str(tmp_path / "web"))
    with pytest.raises(InputError, match=r"rigbuild\.assets\.web install"):
        web.asset_path()
    bad = tmp_path / "three-0.149.0.tgz"
    src = tmp_path / "package" / "build"
    src.mkdir(parents=True)
    (src / "three.min.js").write_text("var THREE = {};")
    with tarfile.open(bad, "w:gz") as tar:
        tar.add(tmp_path / "package", arcname="package")
    with pytest.raises(InputError, match="sha256"):
        web.install(tarball=bad)
    assert not (tmp_path / "web" / "three.min.js").exists()  # nothing half-installed


def _three_js() -> str:
    try:
        return web.asset_path().read_text(encoding="utf-8")
    except InputError as e:
        pytest.skip(f"three.js is not installed: {e}")


@pytest.fixture(scope="module")
def tiny_page(tmp_path_factory):
    root = tmp_path_factory.mktemp("viewer")
    res, rig, takes = tiny_results(root)
    metrics = {"calibration": {"rms_px": 0.1}, "tracking": {"lost_frames": 0, "sequences": {
        "rom00": {"median_residual_mm": 0.3, "frames": 9}}}, "personalization": {"residual_final_mm": 0.4}}
    page = build_report(res, "tiny", metrics, three_js=_three_js())
    out = res / "report.html"
    out.write_text(page)
    return out, rig, takes


def _chromium(*args: str, timeout: int = 180) -> subprocess.CompletedProcess:
    if CHROMIUM is None:
        pytest.skip("Chromium is not installed (apt-get install chromium)")
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
           "--hide-scrollbars", "--window-size=1400,900", "--virtual-time-budget=8000", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


def test_the_page_in_chromium_moves_a_vertex_with_a_slider_plays_a_take_and_has_no_errors(tiny_page):
    html, rig, takes = tiny_page
    assert html.stat().st_size < 5e6
    r = _chromium("--dump-dom", html.as_uri() + "?selfcheck")
    dom = r.stdout
    errors = re.search(r'<pre id="rb-errors"[^>]*data-count="(\d+)"[^>]*>(.*?)</pre>', dom, re.S)
    assert errors and errors.group(1) == "0", (errors.group(2) if errors else dom[-2000:])
    check = json.loads(re.search(r'<pre id="rb-selfcheck"[^>]*>(.*?)</pre>', dom, re.S).group(1))
    assert check["models"] == 3 and check["takes"] == 2 and check["errors"] == 0
    # the slider of the shape with the largest delta moves that delta's vertex by the delta (quantized)
    norms = np.linalg.norm(rig.deltas, axis=2)
    k, v = np.unravel_index(np.argmax(norms), norms.shape)
    s = check["slider"]
    assert s["shape"] == rig.shape_names[k] and s["vertex"] == v
    assert np.allclose(s["before"], rig.neutral[v], atol=0.01)
    assert np.allclose(s["after"], rig.neutral[v] + rig.deltas[k, v], atol=0.01)
    assert s["moved_mm"] == pytest.approx(norms[k, v], abs=0.01)
    # the first take (seol on stylized) at its most active frame: the mesh is where its weights put it
    char, w = takes[take_files(html.parent)[0][0]]
    f = int(np.argmax(np.abs(w).sum(1)))
    assert check["take"]["frame"] == f
    assert check["take"]["max_offset_mm"] == pytest.approx(np.abs(np.einsum("k,kvc->vc", w[f], char.deltas)).max(),
                                                           abs=0.01)
    last_csv, _, _, last_char = take_files(html.parent)[-1]
    assert check["switched"] == {"take": f"perf00 → {last_char} ({last_csv.parts[-4]})",
                                 "model": f"character {last_char} (characters/{last_char}.npz)", "sliders": 3}
    # the summary table ends above the fold of a 1400x900 window
    assert check["summary_bottom_px"] < 900
    if check["webgl"]:  # swiftshader drew the mesh at the centre of the canvas (not the background grey)
        assert check["centre_pixel"][:3] != [244, 244, 244]


def test_the_page_screenshot_at_1400x900_shows_the_summary_and_the_viewer(tiny_page, tmp_path):
    import cv2

    html, _, _ = tiny_page
    shot = tmp_path / "report.png"
    _chromium(f"--screenshot={shot}", html.as_uri())
    img = cv2.imread(str(shot))
    assert img is not None and img.shape[:2] == (900, 1400)
    assert img.std() > 20  # text, badges and the viewer rendered, not a blank page
    badge = np.all(np.abs(img.astype(int) - [208, 245, 216]) <= 3, axis=2)  # the pass colour #d8f5d0 (BGR)
    assert badge[:450].sum() > 200  # pass cells of the summary in the top half


def test_a_page_over_its_size_limit_loads_the_viewer_from_the_folder_beside_it(tiny_page, tmp_path):
    html, rig, _ = tiny_page
    res = html.parent
    assets: dict[str, str] = {}
    page = build_report(res, "tiny", {"calibration": {"rms_px": 0.1}}, three_js=_three_js(), assets=assets,
                        inline_limit_mb=0.05)
    assert set(assets) == {DATA_JS, THREE_JS} and 'id="rb-viewer-data"' not in page
    assert f'<script src="report_files/{DATA_JS}"></script>' in page and len(page) < 0.3e6
    out = tmp_path / "split" / "report.html"
    (out.parent / "report_files").mkdir(parents=True)
    for name, text in assets.items():
        (out.parent / "report_files" / name).write_text(text)
    out.write_text(page)
    dom = _chromium("--dump-dom", out.as_uri() + "?selfcheck").stdout
    assert re.search(r'<pre id="rb-errors"[^>]*data-count="0"', dom), dom[-2000:]
    check = json.loads(re.search(r'<pre id="rb-selfcheck"[^>]*>(.*?)</pre>', dom, re.S).group(1))
    assert check["models"] == 3 and check["slider"]["moved_mm"] == pytest.approx(
        np.linalg.norm(rig.deltas, axis=2).max(), abs=0.01)
    # small enough: everything inline, nothing for the folder
    inline: dict[str, str] = {}
    build_report(res, "tiny", {}, three_js=_three_js(), assets=inline)
    assert inline == {}


def test_write_report_writes_the_page_and_its_folder_and_names_the_install_command(tiny_page, tmp_path,
                                                                                   monkeypatch):
    from rigbuild.report.html import write_report

    res = tiny_page[0].parent
    metrics = tmp_path / "metrics.json"
    metrics.write_text(json.dumps({"calibration": {"rms_px": 0.3}}))
    out = tmp_path / "out" / "report.html"
    _three_js()
    write_report(metrics, res, "tiny", {"sessions": {"tiny": {"thresholds": {"calibration.rms_px": ["max", 0.25, 0.28]}}}},
                 out)
    page = out.read_text()
    assert '<span class="badge fail">session fail · 4 of 5 stages not measured</span>' in page  # the session's limit
    assert "1 from params.report.sessions.tiny" in page and 'id="rb-viewer-data"' in page
    assert [p.name for p in (out.parent / "report_files").iterdir()] == ["README.txt"]
    monkeypatch.setenv("RIGBUILD_WEB", str(tmp_path / "none"))
    with pytest.raises(InputError, match=r"rigbuild\.assets\.web install"):
        write_report(metrics, res, "tiny", {}, tmp_path / "out2" / "report.html")
    assert not (tmp_path / "out2" / "report.html").exists()


def test_the_error_box_records_console_errors_and_uncaught_exceptions(tmp_path):
    """The "no console errors" check can fail: a page with one console.error and one uncaught exception
    reports both."""
    page = build_report(tmp_path, "bad", {"calibration": {"rms_px": 0.1}})
    bad = tmp_path / "bad.html"
    bad.write_text(page.replace("</body>", '<script>console.error("boom"); notAFunction();</script></body>'))
    dom = _chromium("--dump-dom", bad.as_uri()).stdout
    m = re.search(r'<pre id="rb-errors"[^>]*data-count="(\d+)"[^>]*>(.*?)</pre>', dom, re.S)
    assert m and m.group(1) == "2", dom[-2000:]
    assert "console.error: boom" in m.group(2) and "notAFunction" in m.group(2)
