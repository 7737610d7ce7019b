"""Data whose every image the screen leaves out (each disagrees with its own PnP fit far beyond the stated
noise: a pixel_sigma 8 to 50 times too small) are refused as unsolvable in words, exit 3, nothing written;
not an internal error from an empty problem."""
from __future__ import annotations

import json
from dataclasses import replace

import pytest
from incremental_scenes import kaleidoscope

import mirror_fg
from mirror_fg.cli import main
from mirror_fg.core.errors import SolveError
from mirror_fg.io.dataset import dataset_from_dict
from mirror_fg.simulate.tree import simulate_base_case


def test_the_general_view_model_with_every_image_left_out_is_refused_in_words():
    raw = kaleidoscope()  # 0.5 px of noise
    raw["pixel_sigma"] = 0.5 / 8
    with pytest.raises(SolveError, match=r"every image was left out before the solve \(image 'v0': PnP .*pixel_sigma"):
        mirror_fg.calibrate(dataset_from_dict(raw, source="data.json"))


def test_the_tree_with_every_image_left_out_is_refused_in_words():
    dataset, _ = simulate_base_case(num_images=12, num_mirrors=1, num_fiducials=4, seed=1)
    with pytest.raises(SolveError, match="every image was left out before the solve"):
        mirror_fg.calibrate(replace(dataset, pixel_sigma=dataset.pixel_sigma / 50))


def test_cli_exit_3_in_one_line_and_nothing_written(tmp_path, capsys):
    raw = kaleidoscope()
    raw["pixel_sigma"] = 0.5 / 8
    path = tmp_path / "data.json"
    path.write_text(json.dumps(raw))
    out = tmp_path / "result.json"
    assert main(["calibrate", str(path), "-o", str(out), "-q", "--no-ros"]) == 3
    err = [line for line in capsys.readouterr().err.splitlines() if not line.startswith("warning")]
    assert len(err) == 1 and "data.json" in err[0] and "every image was left out" in err[0], err
    assert not out.exists()
