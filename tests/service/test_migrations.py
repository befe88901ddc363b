"""Migrations: upgrade from empty, downgrade to base, through the CLI; schema matches models."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from sqlalchemy import create_engine, inspect

from service.models import Base
from tests.service.conftest import REPO

TABLES = {
    "collections",
    "shapes",
    "jobs",
    "results",
    "result_subjects",
    "idempotency_keys",
    "callback_deliveries",
    "callback_attempts",
}


def _cli(tmp_path: Path, url: str, *args: str) -> str:
    env = {**os.environ, "REGTREE_DATABASE_URL": url, "PYTHONPATH": str(REPO)}
    done = subprocess.run(
        [sys.executable, "-m", "service.cli", "migrate", *args],
        cwd=tmp_path,  # not the repository: the CLI must find the migrations by itself
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


#: The newest migration (migrations/versions).
HEAD = "0006"


def assert_migration_roundtrip(tmp_path: Path, url: str) -> None:
    """Upgrade from empty, schema == models, downgrade to base, upgrade again (any database)."""
    assert _cli(tmp_path, url, "upgrade") == HEAD
    engine = create_engine(url)
    try:
        assert TABLES <= set(inspect(engine).get_table_names())
        with engine.connect() as connection:
            assert compare_metadata(MigrationContext.configure(connection), Base.metadata) == []
        assert _cli(tmp_path, url, "downgrade", "base") == "base"
        assert set(inspect(engine).get_table_names()) <= {"alembic_version"}
        assert _cli(tmp_path, url, "upgrade", "head") == HEAD
        assert _cli(tmp_path, url, "current") == HEAD
    finally:
        engine.dispose()


def test_upgrade_downgrade_roundtrip(tmp_path: Path) -> None:
    assert_migration_roundtrip(tmp_path, f"sqlite:///{tmp_path / 'm.sqlite'}")


def test_default_database_lands_under_var(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k != "REGTREE_DATABASE_URL"}
    env["PYTHONPATH"] = str(REPO)
    done = subprocess.run(
        [sys.executable, "-m", "service.cli", "migrate"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "var" / "regtree.sqlite").is_file()


def test_0003_upgrades_a_database_with_jobs(tmp_path: Path) -> None:
    """Jobs stored at 0002 get their outcome; a running one whose worker is gone is settled
    by the queue after the upgrade (retried), and the queue runs on the upgraded schema."""
    from datetime import datetime, timedelta

    from sqlalchemy import text

    from service import migrate
    from service.core.backoff import Backoff
    from service.core.config import Settings
    from service.db import Database
    from service.jobs.queue import JobQueue, Outcome

    settings = Settings(database_url=f"sqlite:///{tmp_path / 'old.sqlite'}")
    migrate.upgrade(settings, "0002")
    old = datetime(2026, 1, 1)
    rows = [  # (status, started_at, lease_expires_at)
        ("succeeded", old, None),
        ("failed", old, None),
        ("cancelled", None, None),  # cancelled while queued
        ("cancelled", old, None),  # cancelled while running
        ("running", old, old + timedelta(minutes=1)),  # its worker died long ago
        ("queued", None, None),
    ]
    engine = create_engine(settings.database_url)
    with engine.begin() as connection:
        connection.execute(
            text("INSERT INTO collections (name, description, created_at, updated_at) "
                 "VALUES ('c', '', :t, :t)"),
            {"t": old},
        )
        for status, started, lease in rows:
            connection.execute(
                text(
                    "INSERT INTO jobs (collection_id, model_shape_id, shape_ids, method, params,"
                    " status, progress_done, progress_total, attempts, max_attempts, lease_owner,"
                    " lease_expires_at, cancel_requested, created_at, updated_at, started_at)"
                    " VALUES (1, 1, '[1, 2]', 'direct', '{}', :status, 0, 0, :attempts, 3,"
                    " :owner, :lease, :cancel, :t, :t, :started)"
                ),
                {
                    "status": status,
                    "attempts": 0 if started is None else 1,
                    "owner": "gone" if lease else None,
                    "lease": lease,
                    "cancel": status == "cancelled",
                    "t": old,
                    "started": started,
                },
            )
    engine.dispose()

    migrate.upgrade(settings)
    db = Database(settings.database_url)
    try:
        with db.read() as session:
            outcomes = [r[0] for r in session.execute(text("SELECT outcome FROM jobs ORDER BY id"))]
        assert outcomes == ["succeeded", "failed", "cancelled", "aborted", None, None]
        queue = JobQueue(db, backoff=Backoff(0.0, 0.0))
        assert queue.settle_stalled() == {5: Outcome.retrying}
        claimed = [queue.claim("w"), queue.claim("w")]
        assert [(c.job_id, c.attempt) for c in claimed if c] == [(5, 2), (6, 1)]
    finally:
        db.dispose()


def test_0006_a_job_without_a_model_down_and_up(tmp_path: Path) -> None:
    """At 0006 a grouping job stores no model; downgrading to 0005 records its collection's
    first shape (the column is NOT NULL there again), upgrading keeps that shape; a job
    whose collection has lost its shapes gets the first of its own."""
    from sqlalchemy import text

    from service import migrate
    from service.core.config import Settings

    settings = Settings(database_url=f"sqlite:///{tmp_path / 'm6.sqlite'}")
    migrate.upgrade(settings)
    engine = create_engine(settings.database_url)
    job_sql = text(
        "INSERT INTO jobs (collection_id, model_shape_id, shape_ids, method, params, status,"
        " progress_done, progress_total, attempts, max_attempts, cancel_requested, created_at,"
        " updated_at) VALUES (:c, :m, :ids, :method, '{}', 'queued', 0, 0, 0, 3, 0, :t, :t)"
    )
    try:
        with engine.begin() as connection:
            t = "2026-12-01 00:00:00"
            for name in ("kept", "emptied"):
                connection.execute(
                    text("INSERT INTO collections (name, description, created_at, updated_at) "
                         "VALUES (:n, '', :t, :t)"), {"n": name, "t": t})
            for sid in (3, 4):
                connection.execute(
                    text("INSERT INTO shapes (id, collection_id, name, source_format, n_points,"
                         " min_x, min_y, max_x, max_y, points_npy, created_at)"
                         " VALUES (:id, 1, :n, 'txt', 0, 0, 0, 0, 0, x'', :t)"),
                    {"id": sid, "n": f"s{sid}", "t": t})
            rows = [(1, None, "[3, 4]", "grouping"), (2, None, "[8, 9]", "grouping"),
                    (1, 4, "[3, 4]", "direct")]
            for c, m, ids, method in rows:
                connection.execute(job_sql, {"c": c, "m": m, "ids": ids, "method": method,
                                             "t": t})
        read = text("SELECT model_shape_id FROM jobs ORDER BY id")
        with engine.connect() as connection:
            assert [r[0] for r in connection.execute(read)] == [None, None, 4]
        assert _cli(tmp_path, settings.database_url, "downgrade", "0005") == "0005"
        with engine.connect() as connection:
            assert [r[0] for r in connection.execute(read)] == [3, 8, 4]
            nullable = {c["name"]: c["nullable"] for c in inspect(connection).get_columns("jobs")}
            assert nullable["model_shape_id"] is False
        assert _cli(tmp_path, settings.database_url, "upgrade") == HEAD
        with engine.connect() as connection:
            assert [r[0] for r in connection.execute(read)] == [3, 8, 4]
            nullable = {c["name"]: c["nullable"] for c in inspect(connection).get_columns("jobs")}
            assert nullable["model_shape_id"] is True
    finally:
        engine.dispose()
