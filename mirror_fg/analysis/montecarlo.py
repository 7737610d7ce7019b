"""Running Monte Carlo trials (and batches of calibrations): on a Dask cluster, logged as they finish,
resumable, time-boxed.

The engine is ``dask.distributed``: a local cluster of ``jobs`` worker processes by default, or the
scheduler at ``scheduler`` (``tcp://host:8786``) to use a real one. Used by ``scripts/reproduce_fig4.py``,
``scripts/convergence.py`` and ``many.py``; the log is ``trial_log.TrialLog``.

What a fault gives: a scheduler address that is malformed, refuses, is silent or is not a Dask scheduler is a
``DatasetError`` naming it, within ``connect_timeout`` seconds; a local cluster that fails to start (a worker
killed while it starts) is started once more, then the trials run in this process, with a warning; a trial
whose worker keeps dying (Dask's ``KilledWorker``) becomes the record ``on_lost`` makes of it, the others go on.
"""
from __future__ import annotations

import functools
import logging
import os
import socket
import struct
import sys
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path

from tqdm import tqdm

from mirror_fg.core.errors import DatasetError
from mirror_fg.analysis.trial_log import TrialLog

__all__ = ["dask_client", "lost_reason", "run_script", "run_trials", "scheduler_address"]

#: Seconds to wait for a Dask scheduler to answer (``--connect-timeout``).
CONNECT_TIMEOUT_S = 10.0
#: Dask's default scheduler port, taken when an address gives none.
_SCHEDULER_PORT = 8786
#: A Dask handshake is a small message (a few hundred bytes); a first frame longer than this is not Dask's.
_MAX_HANDSHAKE_BYTES = 1 << 20
#: A log level above every message.
_SILENT = logging.CRITICAL + 1
#: Starts of the local cluster before the trials run in this process instead.
_CLUSTER_STARTS = 2


def scheduler_address(address: str) -> tuple[str, str, int]:
    """``(scheme, host, port)`` of a Dask scheduler address ``[tcp://|tls://]HOST[:PORT]``, or a DatasetError."""
    scheme, sep, location = address.strip().rpartition("://")
    scheme = scheme if sep else "tcp"
    host, colon, port_text = location.rpartition(":") if not location.endswith("]") else (location, "", "")
    if not colon:
        host, port_text = location, str(_SCHEDULER_PORT)
    host = host.strip("[]")
    usage = "expected tcp://HOST:PORT, e.g. tcp://127.0.0.1:8786"
    if scheme not in ("tcp", "tls"):
        raise DatasetError(f"scheduler {address!r}: unsupported scheme {scheme!r} ({usage})")
    if not host or any(c.isspace() or c in "/?#@" for c in host):
        raise DatasetError(f"scheduler {address!r}: not an address ({usage})")
    if not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
        raise DatasetError(f"scheduler {address!r}: the port must be a number from 1 to 65535 ({usage})")
    return scheme, host, int(port_text)


def _probe_scheduler(address: str, host: str, port: int, timeout_s: float) -> None:
    """Check that a Dask scheduler listens at ``host:port`` before distributed connects: a Dask server sends
    its handshake first, framed by its length (8 bytes). distributed itself waits for that handshake without a
    time limit (another server's port hangs it) and allocates whatever length it reads (an HTTP reply's
    ``HTTP/1.1`` is 3 EiB)."""
    where = f"scheduler {address}"
    try:
        with socket.create_connection((host, port), timeout=timeout_s) as sock:
            head = b""
            while len(head) < 8:
                chunk = sock.recv(8 - len(head))
                if not chunk:
                    raise DatasetError(f"{where}: the server closed the connection without a Dask handshake "
                                       "(not a Dask scheduler?)")
                head += chunk
    except TimeoutError:
        raise DatasetError(f"{where}: no Dask scheduler answered within {timeout_s:g} s (a firewall, or another "
                           "kind of server on that port?; --connect-timeout SECONDS)") from None
    except socket.gaierror:
        raise DatasetError(f"{where}: unknown host {host!r} (expected tcp://HOST:PORT)") from None
    except OSError as error:
        raise DatasetError(f"{where}: cannot connect ({error.strerror or error})") from None
    (length,) = struct.unpack("Q", head)
    if not 0 < length <= _MAX_HANDSHAKE_BYTES:
        raise DatasetError(f"{where}: the server there is not a Dask scheduler (it answered {head!r})")


@contextmanager
def _quiet_distributed() -> Iterator[None]:
    """distributed's own log lines (a nanny that failed to start, a worker that died and was restarted, a
    client that reconnects) off the console: what they mean is reported once, as a warning or a failed record.
    Its loggers set their own levels, so the handlers distributed installs are the switch (a local cluster
    sets them again: ``silence_logs``)."""
    import distributed  # noqa: F401 - installs its handlers

    handlers = list({id(h): h for name in ("distributed", "distributed.client", "distributed.gc")
                     for h in logging.getLogger(name).handlers}.values())
    levels = [handler.level for handler in handlers]
    for handler in handlers:
        handler.setLevel(_SILENT)
    try:
        yield
    finally:
        for handler, level in zip(handlers, levels):
            handler.setLevel(level)


@contextmanager
def dask_client(scheduler: str | None = None, workers: int = 2, *, connect_timeout: float = CONNECT_TIMEOUT_S):
    """A ``dask.distributed.Client``: of the scheduler at ``scheduler`` (DatasetError if none answers there
    within ``connect_timeout`` seconds), else of a local cluster of ``workers`` single-threaded processes
    (GTSAM's Python factors hold the GIL), closed on exit."""
    with _quiet_distributed():
        if scheduler is not None:
            with _scheduler_client(scheduler, connect_timeout) as client:
                yield client
            return
        cluster = _local_cluster(workers)
        if cluster is None:
            raise RuntimeError(f"the local Dask cluster of {workers} worker(s) did not start")
        with _cluster_client(cluster) as client:
            yield client


@contextmanager
def _scheduler_client(scheduler: str, connect_timeout: float):
    from dask.distributed import Client

    scheme, host, port = scheduler_address(scheduler)
    if scheme == "tcp":
        _probe_scheduler(scheduler, host, port, connect_timeout)
    try:
        client = Client(f"{scheme}://{host}:{port}", timeout=connect_timeout)
    except (OSError, TimeoutError) as error:
        raise DatasetError(f"scheduler {scheduler}: no Dask scheduler answered within {connect_timeout:g} s "
                           f"({error})") from None
    with client:
        yield client


@contextmanager
def _cluster_client(cluster):
    from dask.distributed import Client

    with cluster, Client(cluster) as client:
        yield client


def _local_cluster(workers: int):
    """A started local cluster, or None after ``_CLUSTER_STARTS`` failed starts (a warning says why)."""
    from dask.distributed import LocalCluster

    # A worker process sets up distributed's logging when it imports it, before ``silence_logs`` reaches it:
    # a worker the nanny restarts after a crash logged its INFO lines, and at ERROR a closed-comm traceback
    # ("ConnectionPool is closed", seen in a CI run), to our stderr. The environment reaches every worker
    # process from its start (the user's own setting wins); what a dying worker means is one failed row.
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "critical")
    import dask

    # A worker failing inside distributed as it closes prints its traceback to our stderr through
    # multiprocessing, not logging: worker_stderr.py drops what a closing worker writes (the user's
    # own preloads kept, first).
    preloads = [*dask.config.get("distributed.worker.preload", []), "mirror_fg.analysis.worker_stderr"]
    reason = ""
    for attempt in range(1, _CLUSTER_STARTS + 1):
        try:
            with warnings.catch_warnings(), dask.config.set({"distributed.worker.preload": preloads}):
                # a nanny's HTTP port taken by another cluster: it takes another one
                warnings.filterwarnings("ignore", message="Port .* is already in use", category=UserWarning)
                cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                       dashboard_address=None, silence_logs=_SILENT)
        except (RuntimeError, OSError, TimeoutError) as error:  # "Nanny failed to start." (a worker died)
            reason = f"{type(error).__name__}: {str(error).rstrip('.')}"
            continue
        if attempt > 1:
            warnings.warn(f"the local Dask cluster of {workers} worker(s) did not start at the first try ({reason}); "
                          f"it did at try {attempt}", RuntimeWarning, stacklevel=3)
        return cluster
    warnings.warn(f"the local Dask cluster of {workers} worker(s) did not start in {_CLUSTER_STARTS} tries ({reason}): "
                  "running in this process instead", RuntimeWarning, stacklevel=3)
    return None


def lost_reason(error: BaseException) -> str:
    """A trial's failure outside the trial itself (its worker died), in the user's words."""
    from distributed import KilledWorker

    if isinstance(error, KilledWorker):
        return f"its worker died {error.allowed_failures + 1} times (out of memory?)"
    text = " ".join(str(error).split())
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


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
    log: TrialLog | None = None,
    desc: str = "Monte Carlo runs",
    progress: bool = True,
    jobs: int = 1,
    time_budget_s: float | None = None,
    scheduler: str | None = None,
    connect_timeout: float = CONNECT_TIMEOUT_S,
    on_lost: Callable[[dict, BaseException], dict] | None = None,
) -> list[dict]:
    """Run ``run_trial(**kwargs)`` for every kwargs in ``todo`` and append each record to ``records``.

    run_trial: a picklable top-level function returning a JSON-able dict. total: trials in all (for the
    progress bar; those already in ``records`` count as done). log: an open :class:`TrialLog` each record is
    appended to as it finishes, so an interrupted study resumes (log_path: one opened here, without trial keys).
    jobs: worker processes of the local Dask cluster (1 and no ``scheduler``: in this process). scheduler:
    address of a Dask scheduler to use instead, which must answer within ``connect_timeout`` seconds.
    time_budget_s: no new trial starts after this many seconds; what finished is returned. on_lost: the record
    of a trial whose worker died (``on_lost(kwargs, error)``; default: the error stops the run).
    """
    if log is None and log_path is not None:
        with TrialLog(log_path) as opened:
            return run_trials(run_trial, todo, records, total=total, log=opened, desc=desc, progress=progress,
                              jobs=jobs, time_budget_s=time_budget_s, scheduler=scheduler,
                              connect_timeout=connect_timeout, on_lost=on_lost)
    bar = tqdm(total=total, initial=total - len(todo), desc=desc, unit="run", disable=not progress, file=sys.stderr)
    start = time.monotonic()

    def keep(record: dict) -> None:
        records.append(record)
        if log is not None:
            log.append(record)
        bar.update(1)

    def over_budget() -> bool:
        return time_budget_s is not None and time.monotonic() - start > time_budget_s

    def in_process(queue: list[dict]) -> None:
        for kwargs in queue:
            if over_budget():
                break
            keep(run_trial(**kwargs))

    try:
        if jobs <= 1 and scheduler is None:
            in_process(todo)
        else:
            with _quiet_distributed():
                context: AbstractContextManager | None
                if scheduler is not None:
                    context = _scheduler_client(scheduler, connect_timeout)
                else:
                    cluster = _local_cluster(jobs)
                    context = None if cluster is None else _cluster_client(cluster)
                if context is None:
                    in_process(todo)
                else:
                    with context as client:
                        _on_dask(client, run_trial, todo, jobs, keep, over_budget, on_lost)
    finally:
        bar.close()
    return records


def _on_dask(client, run_trial, todo, jobs, keep, over_budget, on_lost) -> None:
    """Every trial of ``todo`` on ``client``, a bounded number in flight, each record kept as it finishes."""
    from dask.distributed import as_completed

    task = _portable(run_trial)
    width = 2 * max(jobs, sum(client.nthreads().values()))  # in flight: bounded, as the budget needs
    queue = iter(todo)
    pending = as_completed()
    submitted = {}

    def submit(kwargs: dict) -> None:
        future = client.submit(task, pure=False, **kwargs)
        submitted[future.key] = kwargs
        pending.add(future)

    for kwargs in queue:
        submit(kwargs)
        if pending.count() >= width:
            break
    for future in pending:
        try:
            record = future.result()
        except Exception as error:  # the trial's worker died (KilledWorker): its record says so
            if on_lost is None:
                raise
            record = on_lost(submitted[future.key], error)
        del submitted[future.key]
        keep(record)
        if not over_budget():
            following = next(queue, None)
            if following is not None:
                submit(following)


def run_script(main: Callable[[], int]) -> int:
    """A study script's ``main()`` with its errors about the user's files (a damaged or locked log, a full disk)
    as one line and their exit status instead of a traceback."""
    from mirror_fg.core.errors import MirrorFgError

    try:
        return main()
    except MirrorFgError as error:
        print(f"{Path(sys.argv[0]).name}: {error.label}: {' '.join(str(error).split())}", file=sys.stderr)
        return error.exit_code
    except KeyboardInterrupt:
        print(f"{Path(sys.argv[0]).name}: interrupted (run it again to resume)", file=sys.stderr)
        return 130
