"""A full PostgreSQL registry (docs/formats.md "Has it moved?", "Registry"): the real server (conftest's
``postgres_cluster``) answers a record as a full disk does, SQLSTATE 53100 ``disk_full``; the command
writes its result file, exits 2 with one line saying the record was not stored because the disk is full,
and the database holds no part of that record.

Two ways to fill it: a trigger that raises what the server raises when it cannot extend a file (any user),
and a real tablespace on a 1 MiB tmpfs filled to the brim (root only: mounting needs it; skipped saying
so otherwise)."""
from __future__ import annotations

import contextlib
import itertools
import json
import os
import shutil
import subprocess
import tempfile

import pytest
from registry_docs import result_document
from sqlalchemy import text

from mirror_fg.cli import main
from mirror_fg.registry import Registry

_names = itertools.count()

DISK_FULL = """
CREATE FUNCTION no_space() RETURNS trigger AS $$
BEGIN
  RAISE EXCEPTION 'could not extend file "base/1/2": No space left on device'
    USING ERRCODE = 'disk_full', HINT = 'Check free disk space.';
END $$ LANGUAGE plpgsql;
CREATE TRIGGER no_space BEFORE INSERT ON records FOR EACH ROW EXECUTE FUNCTION no_space();
"""


@contextlib.contextmanager
def _tiny_tablespace(cluster, url: str):
    """The registry's tables moved to a tablespace on a 1 MiB tmpfs, then filled until the server says
    the disk is full; skipped where it cannot be mounted."""
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("a tiny tablespace needs a 1 MiB tmpfs, which only root can mount")
    folder = tempfile.mkdtemp(prefix="mirror-fg-tiny-")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", folder], capture_output=True, text=True)
    if done.returncode != 0:
        os.rmdir(folder)
        pytest.skip(f"a tiny tablespace needs a tmpfs: mount failed ({done.stderr.strip()[:100]})")
    try:
        if cluster.user:
            shutil.chown(folder, cluster.user)
        name = f"tiny_{next(_names)}"
        with Registry(url) as registry, registry.engine.connect() as connection:
            connection = connection.execution_options(isolation_level="AUTOCOMMIT")
            connection.execute(text(f"CREATE TABLESPACE {name} LOCATION '{folder}'"))
            for table in ("runs", "records"):
                connection.execute(text(f"ALTER TABLE {table} SET TABLESPACE {name}"))
            connection.execute(text(f"CREATE TABLE filler (x text) TABLESPACE {name}"))
            connection.execute(text("ALTER TABLE filler ALTER COLUMN x SET STORAGE PLAIN"))
            with pytest.raises(Exception, match="No space left on device"):
                for _ in range(1000):  # incompressible rows of ~1 kB until the tmpfs is full
                    connection.execute(text("INSERT INTO filler SELECT string_agg(md5(random()::text), '') "
                                            "FROM generate_series(1, 30)"))
        yield
    finally:
        with contextlib.suppress(Exception), Registry(url) as registry, registry.engine.connect() as connection:
            connection = connection.execution_options(isolation_level="AUTOCOMMIT")
            connection.execute(text("DROP TABLE IF EXISTS filler, records, runs, alembic_version CASCADE"))
        subprocess.run(["umount", "-l", folder], capture_output=True)
        shutil.rmtree(folder, ignore_errors=True)


@contextlib.contextmanager
def _trigger(url: str):
    with Registry(url) as registry, registry.engine.begin() as connection:
        connection.execute(text(DISK_FULL))
    yield


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "bench.json"
    assert main(["simulate", "-o", str(path), "--images", "20", "-q"]) == 0
    return path


@pytest.mark.parametrize("how", ["trigger", "tablespace"])
def test_a_full_postgresql_registry_costs_no_result_file(postgres_cluster, dataset, tmp_path, capsys, how):
    url = postgres_cluster.new_database(f"full_{how}_{next(_names)}")
    with Registry(url) as registry:  # the schema and one record before the disk fills
        registry.record("arm", result_document())
    fill = _trigger(url) if how == "trigger" else _tiny_tablespace(postgres_cluster, url)
    with fill:
        out = tmp_path / "result.json"
        capsys.readouterr()
        status = main(["calibrate", str(dataset), "-o", str(out), "--no-ros", "-q", "--registry", url,
                       "--robot", "arm"])
        [line] = capsys.readouterr().err.splitlines()
        assert status == 2 and "the record was not stored" in line and "disk is full" in line, line
        assert f"{str(out)[-30:]} is written" in line
        assert json.loads(out.read_text())["format"] == "mirror-fg/result@1"
        with Registry(url) as registry:  # the run's row went with its records: nothing of it is there
            assert len(registry.history("arm")) == 1
            with registry.engine.connect() as connection:
                assert connection.execute(text("SELECT count(*) FROM runs")).scalar() == 1
