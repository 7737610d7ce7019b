"""A closing Dask worker's stderr is dropped (mirror_fg/analysis/worker_stderr.py), a working one's kept,
and mirror-fg's local clusters load that preload after the user's own."""
import io
import sys
from types import SimpleNamespace

from mirror_fg.analysis import worker_stderr
from mirror_fg.analysis.montecarlo import _cluster_client, _local_cluster


def test_what_a_closing_worker_writes_is_dropped():
    target, worker = io.StringIO(), SimpleNamespace(status=SimpleNamespace(name="running"))
    stream = worker_stderr._UntilClosing(target, worker)
    stream.write("while working\n")
    for state in ("closing_gracefully", "closing", "closed", "failed"):
        worker.status.name = state
        stream.write(f"Traceback ... {state}\n")
    assert target.getvalue() == "while working\n"


def _stderr_kind() -> str:
    return type(sys.stderr).__name__


def test_local_cluster_workers_carry_the_preload():
    cluster = _local_cluster(1)
    assert cluster is not None
    with _cluster_client(cluster) as client:
        kinds = client.run(_stderr_kind)
    assert list(kinds.values()) == ["_UntilClosing"]
