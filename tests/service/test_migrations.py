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


def assert_migration_roundtrip(tmp_path: Path, url: str) -> None:
    """Upgrade from empty, schema == models, downgrade to base, upgrade again (any database)."""
    assert _cli(tmp_path, url, "upgrade") == "0003"
    engine = create_engine(url)
    try:
        assert TABLES <= set(inspect(engine).get_table_names())
        with engine.connect() as connection:
            assert compare_metadata(MigrationContext.configure(connection), Base.metadata) == []
        assert _cli(tmp_path, url, "downgrade", "base") == "base"
        assert set(inspect(engine).get_table_names()) <= {"alembic_version"}
        assert _cli(tmp_path, url, "upgrade", "head") == "0003"
        assert _cli(tmp_path, url, "current") == "0003"
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
