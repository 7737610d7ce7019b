"""A throwaway PostgreSQL cluster for the registry tests: Debian's server binaries (``postgresql`` package),
``initdb`` into a temporary folder, listening on 127.0.0.1 on a free port, stopped and removed at the end.

As root, the server runs as the ``postgres`` user (``runuser -u postgres --``): PostgreSQL refuses root.
"""
from __future__ import annotations

import glob
import os
import shutil
import socket
import subprocess
import tempfile
import time

__all__ = ["PostgresCluster", "find_binaries"]


def find_binaries() -> str | None:
    """The folder of ``initdb`` and ``pg_ctl`` (the newest Debian version, else the PATH's), or None."""
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(p.split("/")[4]) if
                   p.split("/")[4].isdigit() else 0)
    if found:
        return os.path.dirname(found[-1])
    initdb = shutil.which("initdb")
    return os.path.dirname(initdb) if initdb and shutil.which("pg_ctl") else None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class PostgresCluster:
    """``start()`` a cluster (a RuntimeError saying why it cannot), ``url`` of its ``registry`` database, ``stop()``."""

    def __init__(self, bindir: str) -> None:
        self.bindir = bindir
        self.folder = tempfile.mkdtemp(prefix="mirror-fg-pg-")
        self.data = os.path.join(self.folder, "data")
        self.port = _free_port()
        self.user = "postgres" if os.geteuid() == 0 else None
        self.started = False

    def _run(self, *command: str, timeout: float = 120) -> subprocess.CompletedProcess:
        prefix = ["runuser", "-u", self.user, "--"] if self.user else []
        return subprocess.run(prefix + list(command), capture_output=True, text=True, timeout=timeout)

    def start(self) -> None:
        if self.user:
            shutil.chown(self.folder, self.user)
        done = self._run(os.path.join(self.bindir, "initdb"), "-D", self.data, "-U", "postgres", "--auth=trust",
                         "--encoding=UTF8", "--no-sync")
        if done.returncode != 0:
            raise RuntimeError(f"initdb failed: {(done.stderr or done.stdout).strip()[-300:]}")
        options = f"-c listen_addresses=127.0.0.1 -p {self.port} -k {self.folder} -c fsync=off -c max_connections=60"
        done = self._run(os.path.join(self.bindir, "pg_ctl"), "-D", self.data, "-o", options, "-l",
                         os.path.join(self.folder, "log"), "-w", "-t", "60", "start")
        if done.returncode != 0:
            log = open(os.path.join(self.folder, "log")).read()[-300:] if os.path.exists(os.path.join(self.folder, "log")) else ""
            raise RuntimeError(f"pg_ctl start failed: {(done.stderr or done.stdout).strip()[-200:]} {log}")
        self.started = True
        import psycopg

        deadline = time.monotonic() + 30
        while True:
            try:
                with psycopg.connect(f"host=127.0.0.1 port={self.port} user=postgres dbname=postgres",
                                     autocommit=True) as connection:
                    connection.execute("CREATE DATABASE registry")
                break
            except psycopg.OperationalError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)

    def url(self, database: str = "registry") -> str:
        return f"postgresql://postgres@127.0.0.1:{self.port}/{database}"

    def new_database(self, name: str) -> str:
        """A fresh empty database's URL (each test its own)."""
        import psycopg

        with psycopg.connect(f"host=127.0.0.1 port={self.port} user=postgres dbname=postgres", autocommit=True) as c:
            c.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def stop(self) -> None:
        if self.started:
            self._run(os.path.join(self.bindir, "pg_ctl"), "-D", self.data, "-m", "immediate", "-w", "stop")
            self.started = False
        shutil.rmtree(self.folder, ignore_errors=True)
