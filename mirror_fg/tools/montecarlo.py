"""Running Monte Carlo trials (and batches of calibrations): on a Dask cluster, logged as they finish,
resumable, time-boxed.

The engine is ``dask.distributed``: a local cluster of ``jobs`` worker processes by default, or the
scheduler at ``scheduler`` (``tcp://host:8786``) to use a real one. Used by ``scripts/reproduce_fig4.py``,
``scripts/convergence.py`` and ``tools/many.py``.
"""
from __future__ import annotations

import functools
import json
import sys
import time
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

from tqdm import tqdm

__all__ = ["run_trials", "dask_client"]


@contextmanager
def dask_client(scheduler: str | None = None, workers: int = 2):
    """A ``dask.distributed.Client``: of the scheduler at ``scheduler``, else of a local cluster of
    ``workers`` single-threaded processes (GTSAM's Python factors hold the GIL), closed on exit."""
    from dask.distributed import Client, LocalCluster

    if scheduler is not None:
        client = Client(scheduler)
        try:
            yield client
        finally:
            client.close()
        return
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        with Client(cluster) as client:
            yield client


def _portable(function: Callable[..., dict]) -> Callable[..., dict]:
    """``function`` in a form any worker can run although its module may not be importable there (a
    script loaded from its path, e.g. ``scripts/reproduce_fig4.py``): that module's code travels by
    value (cloudpickle). Without this a worker dies unpickling the task, is restarted, and dies again."""
    import cloudpickle

    module = sys.modules.get(function.__module__)
    if module is None or function.__module__.startswith("mirror_fg"):
        return function
    cloudpickle.register_pickle_by_value(module)
    try:
        blob = cloudpickle.dumps(function)
    finally:
        cloudpickle.unregister_pickle_by_value(module)
    return functools.partial(_run_pickled, blob)


def _run_pickled(blob: bytes, **kwargs: object) -> dict:
    import cloudpickle

    return cloudpickle.loads(blob)(**kwargs)


def run_trials(
    run_trial: Callable[..., dict],
    todo: list[dict],
    records: list[dict],
    *,
    total: int,
    log_path: Path | None = None,
    desc: str = "Monte Carlo runs",
    progress: bool = True,
    jobs: int = 1,
    time_budget_s: float | None = None,
    scheduler: str | None = None,
) -> list[dict]:
    """Run ``run_trial(**kwargs)`` for every kwargs in ``todo`` and append each record to ``records``.

    run_trial: a picklable top-level function returning a JSON-able dict. total: trials in all (for the
    progress bar; those already in ``records`` count as done). log_path: each record is appended to this
    JSON-lines file as it finishes, so an interrupted study resumes. jobs: worker processes of the local
    Dask cluster (1 and no ``scheduler``: in this process). scheduler: address of a Dask scheduler to
    use instead. time_budget_s: no new trial starts after this many seconds; what finished is returned.
    """
    log = open(log_path, "a", encoding="utf-8") if log_path is not None else None
    bar = tqdm(total=total, initial=total - len(todo), desc=desc, unit="run", disable=not progress, file=sys.stderr)
    start = time.monotonic()

    def keep(record: dict) -> None:
        records.append(record)
        if log is not None:
            log.write(json.dumps(record) + "\n")
            log.flush()
        bar.update(1)

    def over_budget() -> bool:
        return time_budget_s is not None and time.monotonic() - start > time_budget_s

    try:
        if jobs <= 1 and scheduler is None:
            for kwargs in todo:
                if over_budget():
                    break
                keep(run_trial(**kwargs))
        else:
            from dask.distributed import as_completed

            task = _portable(run_trial)
            with dask_client(scheduler, jobs) as client:
                width = 2 * max(jobs, sum(client.nthreads().values()))  # in flight: bounded, as the budget needs
                queue = iter(todo)
                pending = as_completed()
                for kwargs in queue:
                    pending.add(client.submit(task, pure=False, **kwargs))
                    if pending.count() >= width:
                        break
                for future in pending:
                    keep(future.result())
                    if not over_budget():
                        following = next(queue, None)
                        if following is not None:
                            pending.add(client.submit(task, pure=False, **following))
    finally:
        bar.close()
        if log is not None:
            log.close()
    return records
