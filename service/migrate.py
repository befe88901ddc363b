"""Apply Alembic migrations without needing ``alembic.ini`` in the working directory.

The migrations live in the top-level ``migrations/`` folder of the repository. They are found,
in order: the ``REGTREE_MIGRATIONS_DIR`` setting, the folder beside this package (a source
checkout or ``pip install -e .``), and ``./migrations`` (the Docker image's working directory).
"""

from __future__ import annotations

from pathlib import Path

from alembic import command
from alembic.config import Config

from service.core.config import Settings


class MigrationsNotFound(RuntimeError):
    pass


def find_migrations_dir(settings: Settings) -> Path:
    candidates: list[Path] = []
    if settings.migrations_dir:
        candidates.append(Path(settings.migrations_dir))
    candidates.append(Path(__file__).resolve().parent.parent / "migrations")
    candidates.append(Path.cwd() / "migrations")
    for candidate in candidates:
        if (candidate / "env.py").is_file():
            return candidate
    tried = ", ".join(str(c) for c in candidates)
    raise MigrationsNotFound(
        f"Alembic migrations folder not found (tried {tried}); set REGTREE_MIGRATIONS_DIR."
    )


def alembic_config(settings: Settings) -> Config:
    config = Config()
    config.set_main_option("script_location", str(find_migrations_dir(settings)))
    config.set_main_option("path_separator", "os")
    # ConfigParser interpolation: a literal % in a URL (password) must be doubled.
    config.set_main_option("sqlalchemy.url", settings.database_url.replace("%", "%%"))
    config.attributes["configure_logging"] = False
    return config


def upgrade(settings: Settings, revision: str = "head") -> None:
    command.upgrade(alembic_config(settings), revision)


def downgrade(settings: Settings, revision: str) -> None:
    command.downgrade(alembic_config(settings), revision)


def current_revision(settings: Settings) -> str | None:
    from alembic.runtime.migration import MigrationContext
    from sqlalchemy import create_engine

    engine = create_engine(settings.database_url)
    try:
        with engine.connect() as connection:
            return MigrationContext.configure(connection).get_current_revision()
    finally:
        engine.dispose()
