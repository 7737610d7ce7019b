"""The public API a new user meets: a clean ``mirror_fg`` namespace whose import loads none of
the heavy stacks, the camera's pose in the base frame as attributes, short reprs, and a capture that
``load_dataset`` names as such and ``load_capture`` detects."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import mirror_fg
from mirror_fg.core.errors import DatasetError

REPO = Path(__file__).resolve().parent.parent
CAPTURE = REPO / "tests" / "data" / "capture" / "takahashi.yaml"

PUBLIC = {
    "__version__", "AnalyticSolution", "Calibration", "Camera", "Dataset", "DatasetError", "Image",
    "IncrementalCalibrator", "MirrorFgError", "Registry", "SolveError", "SolveOptions", "Transform", "calibrate", "calibrate_incremental",
    "dataset_from_dict", "initial_estimate", "load_capture", "load_dataset", "load_result", "save_dataset",
    "solve_analytic", "write_result", "judge",
}
HEAVY = ("matplotlib", "dask", "distributed", "scipy", "cv2", "gtsam", "yaml", "tqdm", "PIL", "numpy", "sqlalchemy",
         "alembic", "psycopg")


def _modules_after(code: str) -> set[str]:
    """Top-level modules loaded by a fresh interpreter running ``code`` from this checkout."""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    probe = code + "\nimport sys, json\nprint(json.dumps(sorted({m.split('.')[0] for m in sys.modules})))"
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env, check=True)
    return set(json.loads(done.stdout.strip().splitlines()[-1]))


def test_the_namespace_holds_only_the_public_names():
    assert set(dir(mirror_fg)) == PUBLIC
    assert set(mirror_fg.__all__) == PUBLIC
    assert not hasattr(mirror_fg, "PackageNotFoundError")
    for name in PUBLIC:  # every one resolves
        assert getattr(mirror_fg, name) is not None
    with pytest.raises(AttributeError):
        mirror_fg.no_such_name  # noqa: B018


@pytest.mark.parametrize("code", ["import mirror_fg", "import mirror_fg.cli", "import mirror_fg; mirror_fg.__version__"])
def test_importing_loads_none_of_the_heavy_stacks(code):
    assert not _modules_after(code) & set(HEAVY)


def test_the_calibration_path_loads_no_plotting_dask_scipy_or_progress_bars():
    loaded = _modules_after("from mirror_fg import calibrate, load_dataset")
    assert not loaded & {"matplotlib", "dask", "distributed", "scipy", "tqdm", "PIL"}


@pytest.fixture(scope="module")
def calibration():
    dataset = mirror_fg.load_dataset(REPO / "examples" / "base_case.json")
    return dataset, mirror_fg.calibrate(dataset)


def test_base_cam_pose_and_covariances_are_attributes_as_in_to_dict(calibration):
    _, cal = calibration
    result = cal.to_dict()
    assert isinstance(cal.T_base_cam, mirror_fg.Transform)
    np.testing.assert_allclose(cal.T_base_cam.R, result["T_base_cam"]["R"], atol=1e-12)
    np.testing.assert_allclose(cal.T_base_cam.t, result["T_base_cam"]["t"], atol=1e-12)
    np.testing.assert_allclose(cal.T_cam_base.t, result["T_cam_base"]["t"], atol=1e-12)
    np.testing.assert_allclose(cal.covariance_base_cam, result["covariance_base_cam"], rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(cal.covariance_cam_base, result["covariance_cam_base"], rtol=1e-12, atol=1e-18)
    # the camera centre in the base frame is where T_cam_base maps to the camera origin
    np.testing.assert_allclose(cal.T_cam_base.apply(cal.T_base_cam.t[None])[0], np.zeros(3), atol=1e-12)


def test_reprs_are_short(calibration):
    dataset, cal = calibration
    for shown in (cal.analytic, cal, dataset):
        assert len(repr(shown)) < 600, type(shown).__name__
    assert "200 image transforms" in repr(cal.analytic)


def test_load_dataset_on_a_capture_points_at_load_capture(tmp_path):
    as_json = tmp_path / "capture.json"
    as_json.write_text(json.dumps({"format": "mirror-fg/capture@1", "num_mirrors": 1}))
    for path in (CAPTURE, as_json):
        with pytest.raises(DatasetError, match="capture file.*load_capture"):
            mirror_fg.load_dataset(path)


def test_load_capture_returns_the_detected_dataset(takahashi_dir):
    dataset = mirror_fg.load_capture(CAPTURE)
    assert isinstance(dataset, mirror_fg.Dataset)
    published = mirror_fg.load_dataset(takahashi_dir / "dataset.json")
    assert len(dataset.images) == len(published.images) == 5
    # the photographs' corners detected: the published corners, labelled alike, within a fraction of a pixel
    for ours, theirs in zip(dataset.images, published.images):
        assert set(ours.observations) == set(theirs.observations)
        for name, uv in theirs.observations.items():
            np.testing.assert_allclose(ours.observations[name], uv, atol=0.5)
