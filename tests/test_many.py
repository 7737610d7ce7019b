"""calibrate_many (analysis/many.py) and the Dask engine of analysis/montecarlo.py on a local cluster of 2 workers."""
from __future__ import annotations

import json

from mirror_fg.io.dataset import dataset_text
from mirror_fg.analysis.many import calibrate_many
from mirror_fg.analysis.montecarlo import run_trials
from mirror_fg.simulate.tree import simulate_base_case


def _square(x: int) -> dict:
    return {"x": x, "y": x * x}


def test_dask_local_cluster_runs_trials_resumably(tmp_path):
    log = tmp_path / "runs.jsonl"
    records = run_trials(_square, [{"x": x} for x in range(6)], [], total=6, log_path=log, progress=False, jobs=2)
    assert sorted(r["y"] for r in records) == [x * x for x in range(6)]
    assert len(log.read_text().splitlines()) == 6


def test_calibrate_many_one_bad_input_among_good_ones(tmp_path):
    inputs = []
    for seed in (1, 2):
        dataset, _ = simulate_base_case(num_images=24, seed=seed)
        path = tmp_path / f"robot{seed}.json"
        path.write_text(dataset_text(dataset))
        inputs.append(path)
    bad = tmp_path / "broken.json"
    bad.write_text('{"format": "mirror-fg/dataset@1", "num_mirrors": 2}')
    inputs.insert(1, bad)
    rows = calibrate_many(inputs, tmp_path / "out", workers=2, progress=False)
    assert [r["status"] for r in rows] == ["ok", "failed", "ok"]
    assert rows[1]["reason"] and rows[1]["result"] is None
    for row in (rows[0], rows[2]):
        result = json.loads(open(row["result"]).read())
        assert result["format"] == "mirror-fg/result@1" and len(row["sigma3_position_mm"]) == 3
