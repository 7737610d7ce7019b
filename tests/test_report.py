"""Tests of mirror_fg.report.writer: residuals, the HTML page (rendered in headless Chromium) and the PDF."""
from __future__ import annotations

import base64
import math
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from mirror_fg import calibrate
from mirror_fg.core.errors import DatasetError
from mirror_fg.core.camera import Camera
from mirror_fg.data import Dataset, Image
from mirror_fg.core.geometry import nested_transform, project, so3_exp
from mirror_fg.report.residuals import OUTLIER_FACTOR, compute_residuals
from mirror_fg.report.writer import write_report
from mirror_fg.core.transform import rotation_to_quaternion_xyzw

PIXEL_SIGMA = 0.5
OUTLIER_IMAGE = "img004"


def _tilted(rng: np.random.Generator, nominal: np.ndarray, distance: float, tilt_deg: float) -> np.ndarray:
    """Mirror vector (camera frame, metres): ``nominal`` tilted up to ``tilt_deg``, length ``distance``."""
    axis = rng.normal(size=3)
    axis -= (axis @ nominal) * nominal
    axis /= np.linalg.norm(axis)
    return distance * (so3_exp(np.deg2rad(tilt_deg) * rng.uniform() * axis) @ nominal)


def _transform_dict(R: np.ndarray, t: np.ndarray) -> dict:
    return {"R": R.tolist(), "t": t.tolist(), "q_xyzw": rotation_to_quaternion_xyzw(R).tolist()}


def make_scene(seed: int = 0, pixel_sigma: float = PIXEL_SIGMA, outlier_px: float = 8.0, camera: bool = True):
    """A small two-mirror scene and a hand-made result@1 at its true values.

    Mirror 1 (behind the camera) has 3 placements, mirror 2 (in front) a new one in each of 9 images;
    4 fiducials and 2 reconstruction points. Observations: true pixels (through a slightly distorting
    camera) plus N(0, pixel_sigma); image OUTLIER_IMAGE gets ``outlier_px`` of noise instead.
    Without ``camera`` the observations are normalized coordinates and the noise is scaled by 1/800.
    """
    rng = np.random.default_rng(seed)
    R = so3_exp(np.deg2rad(30.0) * np.array([1.0, -2.0, 1.0]) / math.sqrt(6.0))
    t = np.array([-0.065, -0.010, -0.060])
    fiducials = {
        "F0": np.array([0.0, 0.0, 0.0]),
        "F1": np.array([0.2, 0.0, 0.0]),
        "F2": np.array([0.0, 0.2, 0.0]),
        "F3": np.array([0.1, 0.1, 0.15]),
    }
    points = {"P0": np.array([0.05, 0.12, 0.03]), "P1": np.array([0.15, 0.05, -0.04])}
    cam = Camera(width=1024, height=768, fx=800.0, fy=800.0, cx=512.0, cy=384.0, dist=(-0.05, 0.01, 0.0, 0.0, 0.0))
    mirrors = {(1, m): _tilted(rng, np.array([0.0, 0.0, -1.0]), 0.5, 15.0) for m in range(3)}
    images = []
    scale = 1.0 if camera else 1.0 / cam.fx
    for i in range(9):
        configs = (i // 3, i)
        mirrors[(2, i)] = _tilted(rng, np.array([0.0, 0.0, 1.0]), 0.5, 15.0)
        A, b = nested_transform(R, t, [mirrors[(1, configs[0])], mirrors[(2, i)]])
        names = list(fiducials) + list(points)
        base = np.array([*fiducials.values(), *points.values()])
        cp = base @ A.T + b
        assert np.all(cp[:, 2] > 0.5)
        z = project(cp)
        if camera:
            z = cam.distort(z)
        image_id = f"img{i:03d}"
        sigma = outlier_px if image_id == OUTLIER_IMAGE else pixel_sigma
        z = z + rng.normal(scale=sigma * scale, size=z.shape)
        images.append(Image(id=image_id, mirror_configs=configs, observations={n: z[k] for k, n in enumerate(names)}))
    ds = Dataset(
        num_mirrors=2, camera=cam if camera else None, pixel_sigma=pixel_sigma * scale,
        fiducials=fiducials, images=images, source="<test scene>",
    )
    # A plausible covariance with correlations, in docs/formats.md's order [dtheta, dt].
    L = np.tril(rng.normal(size=(6, 6))) * np.array([1e-3] * 3 + [2e-3] * 3)[:, None]
    cov = L @ L.T + np.diag([1e-7] * 3 + [1e-6] * 3)
    sd3 = 3.0 * np.sqrt(np.diag(cov))
    R_a = so3_exp(np.array([0.002, -0.001, 0.003])) @ R
    t_a = t + np.array([0.004, -0.002, 0.003])
    result = {
        "format": "mirror-fg/result@1",
        "T_cam_base": _transform_dict(R, t),
        "T_base_cam": _transform_dict(R.T, -R.T @ t),
        "covariance_cam_base": cov.tolist(),
        "sigma3_cam_base": {"rotation_deg": np.rad2deg(sd3[:3]).tolist(), "position_mm": (1e3 * sd3[3:]).tolist()},
        "analytic": {"T_cam_base": _transform_dict(R_a, t_a)},
        "mirrors": [
            {"mirror": l, "config": m, "v": v.tolist(), "sigma3_mm": [1.0, 1.0, 2.0]} for (l, m), v in mirrors.items()
        ],
        "points": {n: {"xyz": p.tolist(), "sigma3_mm": [4.0, 6.0, 10.0]} for n, p in points.items()},
        "optimizer": {"iterations": 4, "initial_error": 120.0, "final_error": 30.0, "converged": True},
        "residuals": {"rms_px": pixel_sigma, "max_px": 3.0 * pixel_sigma},
    }
    return ds, result


# --------------------------------------------------------------------------------------------------
# Residuals


def test_residuals_zero_without_noise():
    ds, result = make_scene(pixel_sigma=0.0, outlier_px=0.0)
    ds.pixel_sigma = 1.0
    res = compute_residuals(result, ds)
    assert res.units == "px"
    assert len(res.names) == 9 * 6
    assert np.max(np.abs(res.residual)) < 1e-9
    assert res.is_fiducial.sum() == 9 * 4


def test_residuals_statistics_and_flagging():
    ds, result = make_scene()
    res = compute_residuals(result, ds)
    per_image = res.per_image_rms()
    assert list(per_image) == [im.id for im in ds.images]
    flagged = res.flagged_images()
    assert list(flagged) == [OUTLIER_IMAGE]
    others = [v for k, v in per_image.items() if k != OUTLIER_IMAGE]
    assert 0.2 < np.sqrt(np.mean(np.square(others))) / PIXEL_SIGMA < 2.0
    assert set(res.per_point_rms()) == {"F0", "F1", "F2", "F3", "P0", "P1"}
    assert flagged[OUTLIER_IMAGE] > OUTLIER_FACTOR * np.median(list(per_image.values()))


def test_residuals_normalized_dataset():
    ds, result = make_scene(camera=False, outlier_px=0.5)
    res = compute_residuals(result, ds)
    assert res.units == "normalized"
    assert 0.3 < res.rms / ds.pixel_sigma < 2.0


def test_residuals_reject_foreign_result():
    ds, result = make_scene()
    result["mirrors"] = [m for m in result["mirrors"] if not (m["mirror"] == 2 and m["config"] == 3)]
    with pytest.raises(DatasetError, match="img003.*mirror 2 configuration 3"):
        compute_residuals(result, ds)
    ds, result = make_scene()
    del result["points"]["P1"]
    with pytest.raises(DatasetError, match="'P1'"):
        compute_residuals(result, ds)


# --------------------------------------------------------------------------------------------------
# Report files


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    ds, result = make_scene()
    out = tmp_path_factory.mktemp("report")
    return write_report(result, ds, out, progress=False)


_IMG_SRC = re.compile(r"<img\b[^>]*\bsrc=['\"]([^'\"]*)['\"]", re.I)


def _assert_self_contained(text: str) -> list[str]:
    """The page loads nothing from outside: every image is a data: URI, no scripts, links or URLs."""
    sources = _IMG_SRC.findall(text)
    assert sources, "no <img> in the page"
    for src in sources:
        assert src.startswith("data:image/png;base64,"), src[:60]
        assert base64.b64decode(src.split(",", 1)[1], validate=True).startswith(b"\x89PNG\r\n\x1a\n")
    lowered = text.lower()
    for forbidden in ("<script", "<link", "<iframe", "http://", "https://", "url("):
        assert forbidden not in lowered, forbidden
    return sources


def test_report_html_content(report):
    text = report["html"].read_text(encoding="utf-8")
    sources = _assert_self_contained(text)
    assert len(sources) == 8  # histogram, per-image, per-point, radial, scene, correlation, error map, validation
    flagged = re.search(r"<ul id='flagged-images'>(.*?)</ul>", text, re.S)
    assert flagged and OUTLIER_IMAGE in flagged.group(1)
    assert "img003" not in flagged.group(1)
    assert "analytic vs MLE: rotation" in text and "<joint" not in text  # the joint is escaped in <pre>
    assert "&lt;joint name=" in text


def test_report_without_dataset(tmp_path):
    _, result = make_scene()
    del result["analytic"], result["covariance_cam_base"]
    result["residuals"]["outliers"] = [{"image": "img001", "point": "F2", "sigmas": 4.25}]
    paths = write_report(result, None, tmp_path / "nested" / "out", progress=False)
    text = paths["html"].read_text(encoding="utf-8")
    assert len(_assert_self_contained(text)) == 1  # the scene only
    assert "No dataset given" in text and "no covariance" in text
    assert "image img001, point F2: 4.25 σ" in text
    assert paths["pdf"].read_bytes().startswith(b"%PDF")


def test_report_shows_what_was_left_out_a_split_and_the_estimated_camera(tmp_path):
    _, result = make_scene()
    result["excluded"] = [{"image": "img004", "point": None, "reason": "PnP reprojection 14.2 px", "sigmas": None}]
    result["inconsistency"] = {"groups": [["img000", "img001"], ["img002"]], "rotation_deg": 3.1, "position_mm": 40.0,
                               "message": "images img000-img001 and img002 disagree by 3.1° / 40 mm: did the camera move?"}
    result["camera"] = {"model": "pinhole", "width": 800, "height": 600, "fx": 801.5, "fy": 799.0, "cx": 401.0,
                        "cy": 298.0, "dist": [-0.21, 0.0, 0.0, 0.0, 0.0], "estimated": ["fx", "k1"],
                        "sigma3": {"fx": 6.0, "k1": 0.03}}
    text = write_report(result, None, tmp_path / "out", progress=False)["html"].read_text(encoding="utf-8")
    excluded = re.search(r"<ul id='excluded'[^>]*>(.*?)</ul>", text, re.S)
    assert excluded and "image img004: PnP reprojection 14.2 px" in excluded.group(1)
    assert "did the camera move?" in re.search(r"<p id='inconsistency'[^>]*>(.*?)</p>", text, re.S).group(1)
    assert "group 2: img002" in text
    camera = re.search(r"<pre id='camera'[^>]*>(.*?)</pre>", text, re.S)
    assert camera and "fx 801.5 px ± 6 px (3σ)" in camera.group(1) and "k1 -0.21 ± 0.03 (3σ)" in camera.group(1)
    verdict = re.search(r"class='verdict (\w+)'", text)
    assert verdict is None or verdict.group(1) != "good"


def test_report_figures_normalized_dataset():
    """Without a camera: normalized units, no image size for the frustum or the residual arrows."""
    from mirror_fg.report.writer import _summary
    from mirror_fg.report.figures import figure_per_point as _figure_per_point
    from mirror_fg.report.figures import figure_scene as _figure_scene
    from mirror_fg.report.figures import png as _png

    ds, result = make_scene(camera=False)
    res = compute_residuals(result, ds)
    summary = _summary(result, ds, res, "base_link")
    assert any("normalized" in label for label, _ in summary.rows)
    for fig in (_figure_per_point(res, ds), _figure_scene(result, ds)):
        assert _png(fig).startswith(b"\x89PNG")


# --------------------------------------------------------------------------------------------------
# Rendering: headless Chromium and poppler


def _chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        path = shutil.which(name)
        if path:
            return path
    return None


def _run_chromium(binary: str, profile: Path, *args: str) -> subprocess.CompletedProcess:
    command = [
        binary, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        "--disable-dev-shm-usage", f"--user-data-dir={profile}", *args,
    ]
    return subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)


# Appended to a copy of the page in the test only (the report itself has no script): records in the
# DOM how many images finished loading with a real size.
_PROBE = """<script>
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var ok = imgs.filter(function (i) { return i.complete && i.naturalWidth > 0 && i.naturalHeight > 0; });
  var p = document.createElement('p');
  p.id = 'probe';
  p.textContent = 'images=' + imgs.length + ' loaded=' + ok.length;
  document.body.appendChild(p);
});
</script>"""


def test_report_renders_in_chromium(report, tmp_path):
    binary = _chromium()
    if binary is None:
        pytest.skip("chromium not installed: apt-get install chromium (CI installs it in .ci/run)")
    import matplotlib.image

    page = report["html"]
    shot = tmp_path / "shot.png"
    run = _run_chromium(binary, tmp_path / "profile1", f"--screenshot={shot}", "--window-size=1200,3000",
                        "--hide-scrollbars", page.resolve().as_uri())
    assert shot.exists(), f"no screenshot; chromium said: {run.stderr[-2000:]}"
    pixels = matplotlib.image.imread(shot)[..., :3]
    assert pixels.shape[:2] == (3000, 1200)
    flat = pixels.reshape(-1, 3)
    assert np.ptp(flat, axis=0).max() > 0.5, "screenshot is blank"
    # The figures put colour on the page (text alone is grey): bars, histograms, mirror patches.
    saturation = flat.max(axis=1) - flat.min(axis=1)
    assert np.mean(saturation > 0.25) > 0.005, "no coloured figure visible in the screenshot"

    probed = tmp_path / "probed.html"
    probed.write_text(page.read_text(encoding="utf-8").replace("</body>", _PROBE + "</body>"), encoding="utf-8")
    run = _run_chromium(binary, tmp_path / "profile2", "--dump-dom", "--virtual-time-budget=5000", probed.as_uri())
    dom = run.stdout
    assert "<html" in dom, f"no DOM dumped; chromium said: {run.stderr[-2000:]}"
    sources = _IMG_SRC.findall(dom)
    assert len(sources) == 8 and all(s.startswith("data:image/png;base64,") for s in sources)  # with the error map, validation
    assert re.search(r"images=8 loaded=8", dom), re.findall(r"<p id=\"probe\">.*?</p>", dom)


def test_report_pdf_pages_render(report, tmp_path):
    pdftoppm = shutil.which("pdftoppm")
    if pdftoppm is None:
        pytest.skip("pdftoppm not installed: apt-get install poppler-utils")
    import matplotlib.image

    pdf = report["pdf"]
    data = pdf.read_bytes()
    assert data.startswith(b"%PDF")
    figures = 6  # every figure in the PDF, several to a page (was one page per figure)
    run = subprocess.run([pdftoppm, "-r", "40", "-png", str(pdf), str(tmp_path / "page")],
                         capture_output=True, text=True, timeout=120, check=False)
    assert run.returncode == 0, run.stderr
    pages = sorted(tmp_path.glob("page*.png"))
    assert len(pages) >= 2
    pdfimages = shutil.which("pdfimages")
    if pdfimages is not None:
        listing = subprocess.run([pdfimages, "-list", str(pdf)], capture_output=True, text=True, timeout=120).stdout
        assert len([line for line in listing.splitlines()[2:] if " image " in line]) >= figures
    sizes = set()
    for page in pages:
        pixels = matplotlib.image.imread(page)[..., :3]
        sizes.add(pixels.shape)
        assert np.ptp(pixels.reshape(-1, 3), axis=0).max() > 0.5, f"{page.name} is blank"
    assert sizes == {(468, 331, 3)}  # every page A4 portrait (8.27 x 11.69 in at 40 dpi)


def test_report_pdf_holds_what_the_html_holds(report, tmp_path):
    """Flagged measurements, ROS snippets, frames, the input echo: in the PDF as in the HTML."""
    pdftotext = shutil.which("pdftotext")
    if pdftotext is None:
        pytest.skip("pdftotext not installed: apt-get install poppler-utils")
    import html as html_module

    run = subprocess.run([pdftotext, "-layout", str(report["pdf"]), "-"], capture_output=True, text=True, timeout=120)
    pdf_text = " ".join(run.stdout.split())
    page = html_module.unescape(report["html"].read_text(encoding="utf-8"))
    flagged = re.search(r"<ul id='flagged-images'>(.*?)</ul>", page, re.S).group(1)
    items = re.findall(r"<li[^>]*>(.*?)</li>", flagged)
    assert items and OUTLIER_IMAGE in items[0]
    for expected in [*items, "Frames: {B} base", "static_transform_publisher --x", "<joint name=",
                     "base_link_to_camera_link", "mirror-fg version", "result file", "camera", "pinhole 1024×768",
                     "Console summary", "T_base_cam 3σ camera position along",
                     "Residual vs distance from the image centre"]:
        assert " ".join(expected.split()) in pdf_text, expected
        assert expected in page, expected


# --------------------------------------------------------------------------------------------------
# On the real pipeline: the simulated base case and the real photographs (Takahashi et al. 2012)


def _check_pipeline_report(ds, result, out: Path, render: bool) -> None:
    from mirror_fg.io.ros import write_ros_outputs

    res = compute_residuals(result, ds)
    # The report recomputes exactly what the calibration reports.
    assert res.rms == pytest.approx(result["residuals"]["rms_px"], rel=1e-9, abs=1e-12)
    assert res.largest == pytest.approx(result["residuals"]["max_px"], rel=1e-9, abs=1e-12)
    ros = write_ros_outputs(result, out / "result.json")
    assert all(p.exists() for p in ros)
    if render:
        paths = write_report(result, ds, out / "report", progress=False)
        text = paths["html"].read_text(encoding="utf-8")
        assert len(_assert_self_contained(text)) == 8  # with the error map and the validation
        assert paths["pdf"].read_bytes().startswith(b"%PDF")


def test_report_simulated_base_case(tmp_path):
    from mirror_fg.simulate.tree import simulate_base_case

    ds, _ = simulate_base_case(num_images=30, num_points=2, pixel_sigma=1.0, seed=3)
    _check_pipeline_report(ds, calibrate(ds).to_dict(), tmp_path, render=False)  # rendering: the fixture


def test_report_real_photographs(takahashi_dir, tmp_path):
    from mirror_fg.io.dataset import load_dataset

    ds = load_dataset(takahashi_dir / "dataset.json")
    _check_pipeline_report(ds, calibrate(ds).to_dict(), tmp_path, render=True)


def test_residuals_use_the_estimated_camera_of_the_result():
    """Where the result estimated the intrinsics, its residuals are computed with them, not the dataset's."""
    ds, result = make_scene()
    true_residuals = compute_residuals(result, ds)
    c = ds.camera
    moved = {"model": c.model, "width": c.width, "height": c.height, "fx": c.fx + 40.0, "fy": c.fy, "cx": c.cx,
             "cy": c.cy, "dist": list(c.dist), "estimated": ["fx"], "sigma3": {"fx": 1.0}}
    with_camera = compute_residuals({**result, "camera": moved}, ds)
    shift = np.linalg.norm(with_camera.predicted - true_residuals.predicted, axis=1)
    assert np.min(shift) > 0.1 and np.median(shift) > 1.0  # fx 40 px off moves every prediction
    same = compute_residuals({**result, "camera": {**moved, "fx": c.fx}}, ds)
    np.testing.assert_allclose(same.predicted, true_residuals.predicted, atol=1e-9)
