"""Running Monte Carlo trials: in parallel processes, logged as they finish, resumable, time-boxed.

Used by ``scripts/reproduce_fig4.py`` and ``scripts/convergence.py``.
"""
from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from pathlib import Path

from tqdm import tqdm

__all__ = ["run_trials"]


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
) -> list[dict]:
    """Run ``run_trial(**kwargs)`` for every kwargs in ``todo`` and append each record to ``records``.

    run_trial: a picklable top-level function returning a JSON-able dict. total: trials in all (for the
    progress bar; those already in ``records`` count as done). log_path: each record is appended to this
    JSON-lines file as it finishes, so an interrupted study resumes. jobs: worker processes.
    time_budget_s: no new trial starts after this many seconds; what finished is returned.
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
        if jobs <= 1:
            for kwargs in todo:
                if over_budget():
                    break
                keep(run_trial(**kwargs))
        else:
            with ProcessPoolExecutor(max_workers=jobs) as pool:
                queue = iter(todo)
                pending = set()
                while True:
                    while len(pending) < 2 * jobs and not over_budget():
                        kwargs = next(queue, None)
                        if kwargs is None:
                            break
                        pending.add(pool.submit(run_trial, **kwargs))
                    if not pending:
                        break
                    finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for future in finished:
                        keep(future.result())
    finally:
        bar.close()
        if log is not None:
            log.close()
    return records
