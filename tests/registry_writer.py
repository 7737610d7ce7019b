"""A registry writer process for the load and kill tests: ``python registry_writer.py URL WRITER COUNT [CAMERAS]
[--slow]`` records COUNT runs tagged ``WRITER-i`` (a rig of CAMERAS cameras); ``--slow`` prints a line after each
insert of a run's camera rows (inside the run's transaction, before its commit) and pauses there, for 30 s
in the third run, so that a test can kill it mid-run."""
from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from registry_docs import result_document  # noqa: E402

from mirror_fg.registry import Registry  # noqa: E402


def main() -> None:
    url, writer, count = sys.argv[1], sys.argv[2], int(sys.argv[3])
    cameras = int(sys.argv[4]) if len(sys.argv) > 4 and not sys.argv[4].startswith("--") else 1
    slow = "--slow" in sys.argv
    registry = Registry(url)
    if slow:
        from sqlalchemy import event

        runs = []

        @event.listens_for(registry.engine, "after_cursor_execute")
        def inserted(conn, cursor, statement, parameters, context, executemany):  # noqa: ANN001
            words = statement.split()
            if words[:3] == ["INSERT", "INTO", "runs"]:
                runs.append(1)
            elif words[:3] == ["INSERT", "INTO", "records"]:
                print(f"inserted camera rows of run {len(runs)}", flush=True)
                time.sleep(0.05 if len(runs) < 3 else 30)

    for i in range(count):
        rig = {f"cam{k}": ((100.0 + k, i, 50.0), (0.0, 0.0, k)) for k in range(cameras)} if cameras > 1 else None
        registry.record("fleet" if not slow else "killed", result_document(tag=f"{writer}-{i}", cameras=rig))
        if slow:
            print(f"committed {writer}-{i}", flush=True)
    registry.close()


if __name__ == "__main__":
    main()


def record_in_worker(url: str, tag: str) -> dict:
    """One recording as calibrate-many makes it in a Dask worker (``registry.cli.record_row``, a new Registry per
    input, after the result file would be written), of a run tagged ``tag``: the error line (None: stored) and the
    worker's process."""
    import os

    from mirror_fg.registry.cli import record_row

    error = record_row(url, "fleet", result_document(tag=tag), f"{tag}.json", f"{tag}.result.json")
    return {"tag": tag, "error": error, "pid": os.getpid()}
