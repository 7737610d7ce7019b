"""The calibration registry's library side (mirror_fg.registry): records, history, latest, the schema and its
migrations, and every database failure as one line, on SQLite always and on a real PostgreSQL server
(conftest's ``postgres_cluster``; skipped with a message where none can start)."""
from __future__ import annotations

import itertools
import sqlite3
from datetime import datetime, timedelta, timezone

import pytest
from registry_docs import result_document, verification_document
from sqlalchemy import inspect, text

from mirror_fg.registry import Registry, RegistryError
from mirror_fg.registry.history import flag_changes, history_csv, history_html, history_lines
from mirror_fg.registry.schema import MIGRATIONS, head_revision, make_engine

_names = itertools.count()


@pytest.fixture(params=["sqlite", "postgresql"])
def url(request, tmp_path) -> str:
    """An empty registry database on each backend."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'registry.db'}"
    cluster = request.getfixturevalue("postgres_cluster")
    return cluster.new_database(f"test_{next(_names)}")


def _t0() -> datetime:
    return datetime(2026, 1, 1, 12, 0, tzinfo=timezone.utc)


def test_record_history_latest(url):
    with Registry(url) as registry:
        if url.startswith("sqlite"):  # a file that is not there is named (a typo in the path)
            with pytest.raises(RegistryError, match="no such database file"):
                registry.history("arm1")
        else:
            assert registry.history("arm1") == []  # an empty database: no records, no error
        rig = {"left": ((100.0, 0.0, 50.0), (0.0, 0.0, 0.0)), "right": ((160.0, 0.0, 50.0), (0.0, 0.0, 5.0))}
        first = registry.record("arm1", result_document(cameras=rig), time=_t0(), sha256="ab" * 32)
        assert [r.camera for r in first] == ["left", "right"] and first[0].run_id == first[1].run_id
        registry.record("arm1", verification_document({"left": "not moved", "right": "moved"}),
                        time=_t0() + timedelta(days=1))
        moved = {"left": ((100.0, 0.0, 50.0), (0.0, 0.0, 0.0)), "right": ((160.0, 20.0, 50.0), (0.0, 0.0, 5.0))}
        registry.record("arm1", result_document(cameras=moved, tag="second"), time=_t0() + timedelta(days=2))
        registry.record("arm2", result_document(), time=_t0())
        history = registry.history("arm1")
        assert [(r.camera, r.kind, r.verdict) for r in history] == [
            ("left", "calibration", None), ("right", "calibration", None), ("left", "verification", "not moved"),
            ("right", "verification", "moved"), ("left", "calibration", None), ("right", "calibration", None)]
        assert history[0].time == _t0() and history[0].time.tzinfo is not None
        assert history[0].input_sha256 == "ab" * 32 and history[0].document is None
        assert history[1].t_m == pytest.approx((0.160, 0.0, 0.050))
        assert history[1].sigma3_position_mm == (3.0, 3.0, 3.0) and history[2].t_m is None
        assert [r.kind for r in registry.history("arm1", "right", kind="verification")] == ["verification"]
        latest = registry.latest("arm1", "right")
        assert latest is not None and latest.document["test_tag"] == "second" and latest.t_m[1] == pytest.approx(0.02)
        assert registry.latest("arm1", kind=None).kind == "calibration"
        assert registry.latest("nobody") is None
        assert registry.robots() == ["arm1", "arm2"]
        assert registry.document(first[0].run_id)["cameras"]["right"]["T_base_cam"]["t"][0] == pytest.approx(0.16)


def test_a_rig_is_recorded_whole_or_not_at_all(url):
    """A camera row that cannot be stored (here: two cameras of one name) takes the run and its other rows with it."""
    from mirror_fg.registry import records

    with Registry(url) as registry:
        registry.record("arm", result_document())
        original = records.camera_rows

        def duplicated(document):
            rows = original(document)
            return rows + [rows[0]]  # violates the unique (run, camera)

        records_before = len(registry.history("arm"))
        try:
            import mirror_fg.registry.store as store

            store.camera_rows = duplicated
            with pytest.raises(RegistryError, match="the record was not stored"):
                registry.record("arm", result_document(cameras={"a": ((0, 0, 0), (0, 0, 0)), "b": ((1, 0, 0), (0, 0, 0))}))
        finally:
            store.camera_rows = original
        assert len(registry.history("arm")) == records_before
        with registry.engine.connect() as connection:
            assert connection.execute(text("SELECT count(*) FROM runs")).scalar() == 1


def _alembic_upgrade(engine, revision: str) -> None:
    from alembic import command
    from alembic.config import Config

    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    with engine.begin() as connection:
        config.attributes["connection"] = connection
        command.upgrade(config, revision)


def test_migrates_from_the_first_schema_keeping_its_data(url):
    engine = make_engine(url)
    _alembic_upgrade(engine, "0001")
    with engine.begin() as connection:
        assert "host" not in {c["name"] for c in inspect(connection).get_columns("runs")}
        connection.execute(text("INSERT INTO runs (robot, kind, time, mirror_fg_version, input_sha256, document) "
                                "VALUES ('old', 'calibration', :t, '0.0.9', NULL, :d)"),
                           {"t": datetime(2025, 6, 1, 8, 0), "d": '{"format": "mirror-fg/result@1"}'})
        connection.execute(text("INSERT INTO records (run_id, robot, camera, kind, time, verdict, tx_m, ty_m, tz_m, "
                                "qx, qy, qz, qw) VALUES ((SELECT id FROM runs WHERE robot = 'old'), 'old', 'camera', 'calibration', :t, 'looks right', "
                                "0.1, 0.2, 0.3, 0, 0, 0, 1)"), {"t": datetime(2025, 6, 1, 8, 0)})
    engine.dispose()
    with Registry(url) as registry:
        registry.record("old", result_document(), time=datetime(2025, 7, 1, tzinfo=timezone.utc))  # migrates first
        history = registry.history("old")
        assert [r.mirror_fg_version for r in history][0] == "0.0.9" and history[0].host is None
        assert history[0].t_m == pytest.approx((0.1, 0.2, 0.3)) and history[1].host
        assert history[0].time == datetime(2025, 6, 1, 8, 0, tzinfo=timezone.utc)
        with registry.engine.connect() as connection:
            assert connection.execute(text("SELECT version_num FROM alembic_version")).scalar() == head_revision()
            indexes = {i["name"]: i["column_names"] for i in inspect(connection).get_indexes("records")}
        assert indexes["ix_records_robot_camera_time"] == ["robot", "camera", "time"]
        assert indexes["ix_records_robot_time_id"] == ["robot", "time", "id"]


def test_migrates_from_the_second_schema_and_back(url):
    """A database at revision 0002 (records written) gains the history-order index at the first write of this
    code, keeps its records and reads them in order; downgraded, it loses only that index."""
    from alembic import command
    from alembic.config import Config

    engine = make_engine(url)
    _alembic_upgrade(engine, "0002")
    engine.dispose()
    with Registry(url) as registry:
        assert registry.history("r") == []  # read at 0002: not migrated by a reader
        with registry.engine.connect() as connection:
            assert connection.execute(text("SELECT version_num FROM alembic_version")).scalar() == "0002"
        times = [_t0() + timedelta(hours=h) for h in (3, 1, 2)]
        registry.record("r", result_document(), time=times[0])  # migrates to the newest revision first
        for when in times[1:]:
            registry.record("r", result_document(), time=when)
        assert [r.time for r in registry.history("r")] == sorted(times)
        with registry.engine.connect() as connection:
            assert connection.execute(text("SELECT version_num FROM alembic_version")).scalar() == head_revision()
            assert "ix_records_robot_time_id" in {i["name"] for i in inspect(connection).get_indexes("records")}
        config = Config()
        config.set_main_option("script_location", str(MIGRATIONS))
        with registry.engine.begin() as connection:
            config.attributes["connection"] = connection
            command.downgrade(config, "0002")
        with registry.engine.connect() as connection:
            indexes = {i["name"] for i in inspect(connection).get_indexes("records")}
        assert "ix_records_robot_time_id" not in indexes and "ix_records_robot_camera_time" in indexes
        assert len(registry.history("r")) == 3


def test_history_reads_in_index_order_on_sqlite(tmp_path):
    """A robot's whole history is read through the (robot, time, id) index: no sort of its records afterwards."""
    from sqlalchemy import select

    from mirror_fg.registry.models import CameraRecord, Run

    url = f"sqlite:///{tmp_path / 'registry.db'}"
    with Registry(url) as registry:
        registry.record("r", result_document())
        query = (select(CameraRecord.id, Run.host).join(Run, Run.id == CameraRecord.run_id)
                 .where(CameraRecord.robot == "r").order_by(CameraRecord.time, CameraRecord.id))
        sql = str(query.compile(registry.engine, compile_kwargs={"literal_binds": True}))
        with registry.engine.connect() as connection:
            plan = " ".join(str(row[-1]) for row in connection.exec_driver_sql("EXPLAIN QUERY PLAN " + sql))
    assert "ix_records_robot_time_id" in plan and "TEMP B-TREE" not in plan, plan


def test_the_models_are_the_migrations(url):
    """An empty database migrated to the newest revision has exactly the tables the models describe."""
    from alembic.autogenerate import compare_metadata
    from alembic.migration import MigrationContext

    from mirror_fg.registry.models import Base

    with Registry(url) as registry:
        registry.record("r", result_document())
        with registry.engine.connect() as connection:
            diff = compare_metadata(MigrationContext.configure(connection), Base.metadata)
    assert diff == []


def test_a_newer_schema_is_refused_in_one_line(url):
    with Registry(url) as registry:
        registry.record("r", result_document())
        with registry.engine.begin() as connection:
            connection.execute(text("UPDATE alembic_version SET version_num = '9999'"))
    with Registry(url) as registry:
        for call in (lambda: registry.record("r", result_document()), lambda: registry.history("r")):
            with pytest.raises(RegistryError) as error:
                call()
            assert "newer than this mirror-fg knows" in str(error.value) and "\n" not in str(error.value)


def test_a_query_that_fails_is_one_line(url):
    """A registry whose records table is gone (its revision still there): history's query fails on the server, one
    RegistryError line with the database's own words (PostgreSQL's rows are read by the driver itself)."""
    with Registry(url) as registry:
        registry.record("r", result_document())
        with registry.engine.begin() as connection:
            connection.execute(text("DROP TABLE records"))
        with pytest.raises(RegistryError) as error:
            registry.history("r")
    message = str(error.value)
    assert "cannot read the history" in message and "records" in message and "\n" not in message, message


def test_unusable_databases_are_one_line(tmp_path, postgres_cluster_or_none):
    path = tmp_path / "ro.db"
    with Registry(f"sqlite:///{path}") as registry:
        registry.record("r", result_document())
    cases = {f"sqlite:///file:{path}?mode=ro&uri=true": "readonly",
             f"sqlite:///{tmp_path / 'no' / 'such.db'}": "does not exist"}
    if postgres_cluster_or_none is not None:
        cases[f"postgresql://postgres@127.0.0.1:{postgres_cluster_or_none.port}/absent"] = "does not exist"
    cases["postgresql://postgres@127.0.0.1:1/registry"] = "connect"  # nothing listens on port 1
    for url, words in cases.items():
        with pytest.raises(RegistryError) as error:
            Registry(url).record("r", result_document())
        assert words in str(error.value).lower() and "\n" not in str(error.value), str(error.value)
    for url in ("mysql://x@y/z", "not a url", "sqlite://"):
        with pytest.raises(RegistryError, match="registry"):
            Registry(url)


def test_a_full_database_is_one_line(tmp_path):
    from sqlalchemy import event

    url = f"sqlite:///{tmp_path / 'full.db'}"
    with Registry(url) as registry:
        registry.record("r", result_document())
        pages = sqlite3.connect(tmp_path / "full.db").execute("PRAGMA page_count").fetchone()[0]
        event.listen(registry.engine, "connect", lambda c, _r: c.execute(f"PRAGMA max_page_count={pages}"))
        big = result_document(tag="x" * 200_000)
        with pytest.raises(RegistryError, match="not stored.*full"):
            registry.record("r", big)
        assert len(registry.history("r")) == 1


@pytest.fixture
def postgres_cluster_or_none(request):
    try:
        return request.getfixturevalue("postgres_cluster")
    except pytest.skip.Exception:
        return None


def test_history_flags_changes_beyond_the_combined_sigma(tmp_path):
    """Consecutive calibrations 2 mm apart (3-sigma 3 mm each: combined 4.24 mm) are consistent; 5 mm and
    0.5 deg (combined 0.42 deg) apart are not."""
    url = f"sqlite:///{tmp_path / 'h.db'}"
    with Registry(url) as registry:
        poses = [((100, 0, 50), (0, 0, 0)), ((102, 0, 50), (0, 0, 0)), ((107, 0, 50), (0, 0, 0)),
                 ((107, 0, 50), (0, 0.5, 0))]
        for day, (position, rotation) in enumerate(poses):
            registry.record("arm", result_document(position, rotation), time=_t0() + timedelta(days=day))
        registry.record("arm", verification_document({"camera": "moved"}), time=_t0() + timedelta(days=4))
        records = registry.history("arm")
    changes = flag_changes(records)
    assert [(c.before.time.day, c.after.time.day) for c in changes] == [(2, 3), (3, 4)]
    assert changes[0].position_mm == pytest.approx((5.0, 0.0, 0.0), abs=1e-9)
    assert changes[0].position_sigma3_mm[0] == pytest.approx(18 ** 0.5)
    assert changes[1].rotation_deg == pytest.approx((0.0, 0.5, 0.0), abs=1e-9)
    lines = history_lines("arm", records, changes)
    assert sum(line.startswith("CHANGED: camera") for line in lines) == 2
    rows = history_csv(records, changes).splitlines()
    assert len(rows) == 6 and rows[0].startswith("time_utc,run,robot,camera,kind,verdict,x_mm")
    assert [row.split(",")[22] for row in rows[1:]] == ["0", "0", "1", "1", "0"]
    assert float(rows[4].split(",")[14]) == pytest.approx(0.5)  # ry from the first calibration
    page = history_html("arm", records, changes, url)
    assert page.count("<img") == 1 and "2 change(s) beyond the combined 3-sigma" in page
