"""Kill a registry writer at every instant, for the kill-safety tests (test_registry_kill.py).

``python registry_killer.py every URL CAMERAS``: for k = 1, 2, ... a forked child records one run (a rig of
CAMERAS cameras, tagged ``k<k>``) and SIGKILLs itself at its k-th boundary: after each statement the
driver executed, just before each commit and just after it; it stops at the first k the record outlives,
printing ``killed <k>`` per killed child and ``whole <k>`` for the last.
``python registry_killer.py fresh URL_PATTERN CAMERAS``: the same, each k on its own empty database
(``URL_PATTERN`` with ``{k}``; PostgreSQL databases are created here), so the kills fall in the migrations too.
``python registry_killer.py random URL CAMERAS TIMES SEED``: TIMES children each record runs (tagged
``r<i>-<j>``) in a loop until the parent SIGKILLs them at a random instant (0-0.4 s after the first record).

The parent is one thread (it only forks and waits), so forking it is safe.
"""
from __future__ import annotations

import os
import random
import signal
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from registry_docs import result_document  # noqa: E402
from sqlalchemy import event  # noqa: E402
from sqlalchemy.orm import Session  # noqa: E402

from mirror_fg.registry import Registry  # noqa: E402

ROBOT = "killed"


def _document(tag: str, cameras: int) -> dict:
    rig = {f"cam{c}": ((100.0 + c, 0.0, 50.0), (0.0, 0.0, float(c))) for c in range(cameras)} if cameras > 1 else None
    return result_document(tag=tag, cameras=rig)


def _record_killed_at(url: str, k: int, tag: str, cameras: int) -> None:
    """In a forked child: record, SIGKILLing this process at the k-th boundary (module docstring)."""
    registry = Registry(url)
    count = [0]

    def boundary(*_: object) -> None:
        count[0] += 1
        if count[0] == k:
            os.kill(os.getpid(), signal.SIGKILL)

    event.listen(registry.engine, "after_cursor_execute", boundary)
    event.listen(registry.engine, "commit", boundary)  # before the driver's commit
    event.listen(Session, "after_commit", boundary)  # after it
    registry.record(ROBOT, _document(tag, cameras))
    os._exit(0)


def _fork(work) -> int:
    pid = os.fork()
    if pid == 0:
        try:
            work()
        except BaseException as error:  # noqa: BLE001 - the child reports and dies; the parent sees its status
            print(f"child error {error!r}"[:500], flush=True)
            os._exit(3)
        os._exit(0)
    return pid


def _status(pid: int) -> str:
    _, status = os.waitpid(pid, 0)
    if os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL:
        return "killed"
    return "whole" if os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0 else f"failed {status}"


def _create_database(url: str) -> None:
    if not url.startswith("postgresql"):
        return
    import psycopg

    base, name = url.rsplit("/", 1)
    host = base.split("@", 1)[1]
    address, port = host.split(":")
    with psycopg.connect(f"host={address} port={port} user=postgres dbname=postgres", autocommit=True) as c:
        c.execute(f'CREATE DATABASE "{name}"')


def main() -> None:
    mode, url, cameras = sys.argv[1], sys.argv[2], int(sys.argv[3])
    if mode in ("every", "fresh"):
        for k in range(1, 500):
            target = url.format(k=k) if mode == "fresh" else url
            if mode == "fresh":
                _create_database(target)
            status = _status(_fork(lambda target=target, k=k: _record_killed_at(target, k, f"k{k}", cameras)))
            print(f"{status} {k}", flush=True)
            if status != "killed":
                return
        print("no record outlived 500 boundaries", flush=True)
    elif mode == "random":
        times, rng = int(sys.argv[4]), random.Random(int(sys.argv[5]))
        for i in range(times):
            ready, told = os.pipe()

            def loop(i: int = i, told: int = told) -> None:
                registry = Registry(url)
                for j in range(10_000):
                    registry.record(ROBOT, _document(f"r{i}-{j}", cameras))
                    if j == 0:  # recording: the kill may come
                        os.write(told, b".")
            pid = _fork(loop)
            os.read(ready, 1)
            os.close(ready)
            os.close(told)
            time.sleep(rng.uniform(0.0, 0.4))
            os.kill(pid, signal.SIGKILL)
            print(f"{_status(pid)} {i}", flush=True)


if __name__ == "__main__":
    main()
