"""The report's verdict as a headline and bullets, its progress per figure, each figure rendered once,
and several plots to a PDF page."""
from __future__ import annotations

import collections
import re
import shutil
import subprocess

import pytest

import mirror_fg
from mirror_fg.report.writer import _summary, write_report
from mirror_fg.report.residuals import compute_residuals

from test_report import make_scene

FIGURES = 8  # the scene's report: histogram, per image, per point, radial, 3D scene, correlation, error map, validation


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """The report of the small scene, with progress on, and how many PNGs matplotlib rendered."""
    from matplotlib.figure import Figure

    ds, result = make_scene()
    renders = collections.Counter()
    original = Figure.savefig

    def counting(self, fname, *args, **kwargs):
        renders[kwargs.get("format")] += 1
        return original(self, fname, *args, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Figure, "savefig", counting)
        import io
        import sys

        err = io.StringIO()
        patch.setattr(sys, "stderr", err)
        paths = write_report(result, ds, tmp_path_factory.mktemp("report"), progress=True)
    return paths, renders, err.getvalue()


def test_each_figure_is_rendered_once_for_both_pages(written):
    paths, renders, _ = written
    assert len(re.findall(r"<img\b", paths["html"].read_text(encoding="utf-8"))) == FIGURES
    assert renders["png"] == FIGURES  # was twice each: once for the HTML, again for the PDF


def test_progress_names_each_figure(written):
    _, _, err = written
    for heading in ("residual distribution", "per-image residuals", "per-point residuals", "3d scene",
                    "covariance correlation"):
        assert heading in err, err[-500:]


def test_several_plots_share_a_pdf_page(written):
    pdfimages = shutil.which("pdfimages")
    if pdfimages is None:
        pytest.skip("pdfimages not installed: apt-get install poppler-utils")
    paths, _, _ = written
    listing = subprocess.run([pdfimages, "-list", str(paths["pdf"])], capture_output=True, text=True, check=True)
    pages = [int(line.split()[0]) for line in listing.stdout.splitlines()[2:] if line.split()[2] == "image"]
    assert len(pages) == FIGURES
    assert max(collections.Counter(pages).values()) >= 2, pages


def test_verdict_is_a_headline_with_bullets(written):
    paths, _, _ = written
    page = paths["html"].read_text(encoding="utf-8")
    verdict = re.search(r"<div class='verdict (\w+)'><strong>(.*?)</strong><ul>(.*?)</ul></div>", page, re.S)
    assert verdict, page[:3000]
    bullets = re.findall(r"<li>(.*?)</li>", verdict.group(3))
    assert len(bullets) >= 3 and any("RMS" in b for b in bullets)
    # the scene has a noisy image (make_scene's outlier): the headline names that problem
    assert verdict.group(1) == "bad" and "much worse than the others" in verdict.group(2)


def test_real_photographs_headline_names_the_distortion_and_the_key_to_set(takahashi_dir):
    ds = mirror_fg.load_dataset(takahashi_dir / "dataset.json")
    result = mirror_fg.calibrate(ds).to_dict()
    summary = _summary(result, ds, compute_residuals(result, ds), "base_link")
    assert not summary.good
    assert summary.headline.startswith("Check before use:") and "distortion" in summary.headline
    (radial,) = [r for r in summary.reasons if "grows towards the edge" in r]
    assert "camera.estimate: [k1, k2]" in radial
    assert summary.reasons.index(radial) < next(i for i, r in enumerate(summary.reasons) if "converged" in r)


def test_distortion_advice_names_the_terms_not_yet_estimated(takahashi_dir):
    import json

    data = json.loads((takahashi_dir / "dataset.json").read_text())
    data["camera"]["estimate"] = ["k1", "k2"]
    ds = mirror_fg.io.dataset.dataset_from_dict(data)
    result = mirror_fg.calibrate(ds).to_dict()
    summary = _summary(result, ds, compute_residuals(result, ds), "base_link")
    (radial,) = [r for r in summary.reasons if "towards the edge" in r]
    assert "camera.estimate: [k1, k2, k3, p1, p2]" in radial, radial
