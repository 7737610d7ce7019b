"""How fast the calibration registry answers ``history`` for a robot with many records, on SQLite and (when the
server binaries are there) a throwaway PostgreSQL cluster: the goal is 10,000 records in at most 0.2 s.

    PYTHONPATH=. python scripts/benchmark_registry.py [--records 10000] [--repeats 5] [--no-postgres]

It fills a fresh database with one robot's records (a rig of two cameras, so 5,000 runs for 10,000 records,
among 5 other robots' records; written through the models in one transaction: the fill is not what is timed), then
times ``Registry.history(robot)`` (all the records, without their documents, through the (robot, camera, time)
index) and ``Registry.history(robot, camera)``, best and median of the repeats; and the 8 x 250 concurrent
writers as tests/test_registry_load.py runs them, timed here.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

from registry_docs import result_document  # noqa: E402

from mirror_fg.registry import Registry  # noqa: E402

GOAL_S = 0.2


def fill(url: str, records: int) -> float:
    """``records`` records of robot ``arm-0`` (2 cameras per run) and a fifth as many of 5 other robots; seconds."""
    from sqlalchemy.orm import Session

    from mirror_fg.registry.models import Run
    from mirror_fg.registry.records import camera_rows
    from mirror_fg.registry.store import _record_of

    start = time.perf_counter()
    t0 = datetime(2026, 1, 1, tzinfo=timezone.utc)
    with Registry(url) as registry:
        registry.record("arm-0", result_document(), time=t0 - timedelta(days=1))  # creates the schema
        with Session(registry.engine) as session, session.begin():
            for run in range(records // 2 - 1):
                for robot in ("arm-0",) + (tuple(f"arm-{k}" for k in range(1, 6)) if run % 5 == 0 else ()):
                    rig = {"left": ((100.0 + 0.01 * run, 0.0, 50.0), (0.0, 0.0, 0.0)),
                           "right": ((160.0, 0.0, 50.0), (0.0, 0.0, 5.0))}
                    document, when = result_document(cameras=rig), t0 + timedelta(hours=run)
                    row = Run(robot=robot, kind="calibration", time=when, mirror_fg_version="bench", document=document,
                              input_sha256="0" * 64, host="bench")
                    row.records = [_record_of(robot, "calibration", when, r) for r in camera_rows(document)]
                    session.add(row)
        registry.record("arm-0", result_document(), time=t0 + timedelta(days=9999))
    return time.perf_counter() - start


def time_history(url: str, repeats: int, camera: str | None = None) -> tuple[float, float, float, int]:
    """Best and median wall-clock seconds of ``history``, the best CPU seconds of this process (on a machine
    shared with other work the wall clock also counts their turns), and the records returned."""
    times, cpu, count = [], [], 0
    with Registry(url) as registry:
        registry.history("arm-0", camera)  # the first connection and the schema check, once
        for _ in range(repeats):
            start, start_cpu = time.perf_counter(), time.process_time()
            count = len(registry.history("arm-0", camera))
            times.append(time.perf_counter() - start)
            cpu.append(time.process_time() - start_cpu)
    return min(times), statistics.median(times), min(cpu), count


def writers(url: str, processes: int = 8, each: int = 250) -> tuple[float, int]:
    start = time.perf_counter()
    procs = [subprocess.Popen([sys.executable, str(REPO / "tests" / "registry_writer.py"), url, f"w{n}", str(each)])
             for n in range(processes)]
    assert all(p.wait() == 0 for p in procs)
    seconds = time.perf_counter() - start
    with Registry(url) as registry:
        return seconds, len(registry.history("fleet"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--records", type=int, default=10_000)
    parser.add_argument("--repeats", type=int, default=25)
    parser.add_argument("--no-postgres", action="store_true")
    parser.add_argument("--no-writers", action="store_true")
    args = parser.parse_args()
    cluster = None
    with tempfile.TemporaryDirectory() as folder:
        urls = {"sqlite": f"sqlite:///{folder}/registry.db"}
        if not args.no_postgres:
            from postgres_cluster import PostgresCluster, find_binaries

            bindir = find_binaries()
            if bindir is None:
                print("PostgreSQL: no server binaries, skipped")
            else:
                cluster = PostgresCluster(bindir)
                try:
                    cluster.start()
                    urls["postgresql"] = cluster.url()
                except (RuntimeError, OSError, subprocess.SubprocessError) as error:
                    print(f"PostgreSQL: the throwaway cluster cannot start ({str(error)[:200]}), skipped")
                    cluster.stop()
                    cluster = None
        figures = []
        try:
            for name, url in urls.items():
                filled = fill(url, args.records)
                best, median, cpu, count = time_history(url, args.repeats)
                best_cam, median_cam, cpu_cam, count_cam = time_history(url, args.repeats, "left")
                load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
                print(f"{name}: filled {count} records of arm-0 (+ others) in {filled:.1f} s (load average "
                      f"{load:.1f} on {os.cpu_count()} cores); history(arm-0, left), {count_cam} records: best "
                      f"{best_cam * 1000:.0f} ms, median {median_cam * 1000:.0f} ms, CPU {cpu_cam * 1000:.0f} ms")
                figures.append((name, count, best, median, cpu))
                if not args.no_writers:
                    writer_url = (f"sqlite:///{folder}/writers.db" if name == "sqlite"
                                  else cluster.new_database("writers"))  # type: ignore[union-attr]
                    seconds, stored = writers(writer_url)
                    print(f"{name}: 8 writer processes x 250 records: {stored} stored in {seconds:.1f} s")
        finally:
            for name, count, best, median, cpu in figures:  # the figure, last and alone on its line
                verdict = "meets" if best <= GOAL_S else "MISSES"
                print(f"history of {count} records, {name}: {best * 1000:.0f} ms wall (best of {args.repeats}; median "
                      f"{median * 1000:.0f} ms), {cpu * 1000:.0f} ms CPU: {verdict} the {GOAL_S * 1000:.0f} ms goal")
            if cluster is not None:
                cluster.stop()


if __name__ == "__main__":
    main()
