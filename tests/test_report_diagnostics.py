"""The report's diagnostics: residual vs distance from the image centre, the camera's pose
uncertainty drawn at visible scale, sampled placements, tracked points, the input echo and one RMS."""
from __future__ import annotations

import copy
import re

import numpy as np
import pytest

import mirror_fg
from mirror_fg.report.writer import _summary, write_report
from mirror_fg.report.figures import MAX_PLACEMENTS_DRAWN, _nice_scale, figure_scene
from mirror_fg.report.residuals import Residuals, compute_residuals
from mirror_fg.vision.tracking import Track, TrackSample

from test_report import make_scene


def _residuals(grow: float, n: int = 600, seed: int = 0) -> Residuals:
    """Observed points uniform on a 1000 x 1000 image; residual sigma 0.5 px times (1 + grow * r / r_max)."""
    rng = np.random.default_rng(seed)
    observed = rng.uniform(0, 1000, size=(n, 2))
    r = np.linalg.norm(observed - 500.0, axis=1)
    scale = 0.5 * (1.0 + grow * r / r.max())
    return Residuals(units="px", image_ids=["i"] * n, names=[f"p{k}" for k in range(n)],
                     is_fiducial=np.ones(n, dtype=bool), observed=observed,
                     predicted=observed + rng.normal(size=(n, 2)) * scale[:, None], sigma=0.5)


def test_radial_growth_is_detected_and_noise_is_not():
    grows = _residuals(grow=1.5).radial_profile((500.0, 500.0))
    assert grows.significant and grows.ratio > 1.3 and grows.p_value < 1e-6
    assert np.all(np.diff(grows.rms[:4]) > 0)
    for seed in range(5):
        flat = _residuals(grow=0.0, seed=seed).radial_profile((500.0, 500.0))
        assert not flat.significant, (seed, flat.ratio, flat.p_value)
    assert _residuals(grow=0.0, n=5).radial_profile((500.0, 500.0)) is None


def test_real_photographs_verdict_names_the_distortion_signature(takahashi_dir):
    ds = mirror_fg.load_dataset(takahashi_dir / "dataset.json")
    result = mirror_fg.calibrate(ds).to_dict()
    res = compute_residuals(result, ds)
    profile = res.radial_profile((ds.camera.cx, ds.camera.cy))
    assert profile.inner_rms == pytest.approx(0.44, abs=0.05) and profile.outer_rms == pytest.approx(1.0, abs=0.1)
    summary = _summary(result, ds, res, "base_link")
    assert "grows towards the edge" in summary.verdict and "distortion model" in summary.verdict
    assert not summary.good


def test_one_rms_in_the_summary_table():
    ds, result = make_scene()
    summary = _summary(result, ds, compute_residuals(result, ds), "base_link")
    labels = [label for label, _ in summary.rows if re.search(r"\bRMS\b", label)]
    assert len(labels) == 1 and "√2·σ" in labels[0]
    assert "no significant growth" in summary.verdict or "grows towards" in summary.verdict


def test_pose_uncertainty_is_drawn_at_visible_scale():
    assert [_nice_scale(x) for x in (0.3, 1.0, 1.2, 3.0, 7.0, 12.0, 450.0)] == [1, 1, 2, 5, 10, 20, 500]
    ds, result = make_scene()
    fig = figure_scene(result, ds)
    title = fig.get_suptitle().replace("\n", " ")
    k_pos = float(re.search(r"ellipsoid drawn × ([\d.]+)", title).group(1))
    k_rot = float(re.search(r"cone drawn × ([\d.]+)", title).group(1))
    labels = fig.axes[0].get_legend_handles_labels()[1]
    assert f"camera position 3σ ellipsoid × {k_pos:g}" in labels and f"optical-axis 3σ cone × {k_rot:g}" in labels
    # Drawn size: at least 6 % of the scene for the ellipsoid (mm-sized otherwise on a 0.5 m plot).
    semi = np.array([float(x) for x in re.search(r"semi-axes \[([^\]]*)\] mm", title).group(1).split(",")])
    assert k_pos * semi.max() * 1e-3 >= 0.06 * 0.5 * 0.9


def test_thousands_of_placements_are_sampled():
    ds, result = make_scene()
    rng = np.random.default_rng(1)
    many = copy.deepcopy(result)
    v = rng.normal(size=(3000, 3))
    v[:, 2] = np.abs(v[:, 2]) + 2.0
    v *= 0.5 / np.linalg.norm(v, axis=1)[:, None]
    many["mirrors"] = [{"mirror": 1, "config": k, "v": x.tolist()} for k, x in enumerate(v)]
    fig = figure_scene(many, None)
    labels = fig.axes[0].get_legend_handles_labels()[1]
    assert f"mirror 1 (3000 placements, {MAX_PLACEMENTS_DRAWN} drawn, all as dots)" in labels
    squares = [c for c in fig.axes[0].collections if type(c).__name__ == "Poly3DCollection"]
    assert len(squares) == MAX_PLACEMENTS_DRAWN


def _track(name: str, frames: int, drift: float) -> Track:
    samples = [TrackSample(frame=0, raw=None, refined=np.array([100.0, 200.0]))]
    for f in range(1, frames):
        refined = np.array([100.0 + 5 * f, 200.0 + 2 * f])
        samples.append(TrackSample(frame=f, raw=refined + drift * f / frames, refined=refined, residual_px=0.05 + 0.01 * f))
    return Track(name=name, kind="corner", anchor=samples[0].refined, history=samples)


def test_report_draws_tracks_and_echoes_inputs(tmp_path):
    ds, result = make_scene()
    tracks = {"P0": _track("P0", 30, 1.0), "P1": _track("P1", 20, 0.3)}
    paths = write_report(result, ds, tmp_path, progress=False, tracks=tracks, source="calib.json",
                         inputs={"capture file": "capture.yaml"})
    page = paths["html"].read_text(encoding="utf-8")
    assert len(re.findall(r"<img ", page)) == 9 and "<h2>Tracked points</h2>" in page  # 7 + the error map and the held-out ratios
    inputs = re.search(r"<table class='summary' id='inputs'>(.*?)</table>", page, re.S).group(1)
    for expected in ("calib.json", "&lt;test scene&gt;", "pinhole 1024×768", "4 fiducials", "capture.yaml",
                     mirror_fg.__version__, "UTC"):
        assert expected in inputs, expected
    empty = write_report(result, ds, tmp_path / "none", progress=False, tracks={})
    assert "follows no point" in empty["html"].read_text(encoding="utf-8")
