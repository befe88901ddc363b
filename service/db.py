"""Database engine and sessions.

SQLite is the embedded default. Its connections are opened in WAL mode with a busy timeout and
foreign keys on, and pysqlite's own transaction handling is switched off so that we can emit
``BEGIN IMMEDIATE`` for write transactions: a writer takes the write lock when it starts, not
half-way through, so two writers queue on the busy timeout instead of one failing with
"database is locked" on lock upgrade (the SQLAlchemy pysqlite "serializable isolation" recipe).

PostgreSQL (``postgresql+psycopg://user:password@host/db``) works with the same code: its
transactions are READ COMMITTED, so the few places that must not race say so themselves, in a
form that SQLite ignores or does not need: the job queue claims with ``FOR UPDATE SKIP
LOCKED`` (:mod:`service.jobs.queue`), an ``Idempotency-Key`` is serialised with a
transaction-level advisory lock (:mod:`service.api.idempotency`), and read-modify-write
routes lock their row with ``FOR UPDATE``. ``SELECT ... FOR UPDATE`` compiles to plain
``SELECT`` on SQLite, where ``BEGIN IMMEDIATE`` already serialises every writer.

Use :meth:`Database.read` for reads and :meth:`Database.write` for anything that writes.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

import orjson
from sqlalchemy import Engine, Select, create_engine, event, make_url
from sqlalchemy.orm import Session, sessionmaker

T = TypeVar("T")

_WRITE_OPTION = "regtree_write"


def _is_sqlite(url: str) -> bool:
    return make_url(url).get_backend_name() == "sqlite"


def is_postgresql_url(url: str) -> bool:
    """Whether a database URL names PostgreSQL."""
    return make_url(url).get_backend_name() == "postgresql"


def is_postgresql(session: Session) -> bool:
    """Whether a session talks to PostgreSQL."""
    return bool(session.get_bind().dialect.name == "postgresql")


def lock_first(session: Session, statement: Select[T]) -> T | None:
    """The first row ``statement`` selects that no other transaction holds, locked until
    this one ends: ``FOR UPDATE SKIP LOCKED`` on PostgreSQL (concurrent claimers each get
    another row); on SQLite ``BEGIN IMMEDIATE`` already serialises the writers."""
    return session.scalars(statement.limit(1).with_for_update(skip_locked=True)).first()


def ensure_sqlite_dir(url: str) -> None:
    """Create the folder of a file-backed SQLite URL (``./var`` by default)."""
    parsed = make_url(url)
    if parsed.get_backend_name() == "sqlite" and parsed.database not in (None, "", ":memory:"):
        Path(str(parsed.database)).expanduser().parent.mkdir(parents=True, exist_ok=True)


#: orjson's options for the JSON columns: keys that are not strings written as strings,
#: and numpy arrays and scalars as lists and numbers (what ``json.dumps`` did after
#: ``tolist()``).
_ORJSON_OPTIONS = orjson.OPT_NON_STR_KEYS | orjson.OPT_SERIALIZE_NUMPY


def dumps_json(value: Any) -> str:
    """A JSON column's text: orjson, with the standard library's ``json.dumps`` for what
    orjson refuses (integers beyond 64 bits, say).

    A full result's subjects are about 27 MB of floats (73 glyphs at their stored
    resolution): ``json.dumps`` took 1.8 s of every such job's end, orjson 0.09 s. Non-finite
    floats become ``null`` (the documents are made JSON-safe before they get here)."""
    try:
        return orjson.dumps(value, option=_ORJSON_OPTIONS).decode()
    except TypeError:  # orjson.JSONEncodeError is one
        return json.dumps(value)


def loads_json(text: str | bytes) -> Any:
    """A JSON column's value: orjson (3x faster than ``json.loads`` on a full result), with
    ``json.loads`` for text orjson rejects (``NaN`` written by ``json.dumps`` before)."""
    try:
        return orjson.loads(text)
    except orjson.JSONDecodeError:
        return json.loads(text)


def create_db_engine(url: str, *, busy_timeout_ms: int = 30_000) -> Engine:
    """Create an engine; for SQLite, set up WAL, busy timeout, foreign keys and BEGIN modes.

    JSON columns go through :func:`dumps_json` and :func:`loads_json`."""
    codec: dict[str, Any] = {"json_serializer": dumps_json, "json_deserializer": loads_json}
    if not _is_sqlite(url):
        # A server database: pre-ping so that a connection the server dropped (restart,
        # idle timeout) is replaced instead of failing the next request.
        return create_engine(url, pool_pre_ping=True, **codec)

    ensure_sqlite_dir(url)
    engine = create_engine(
        url,
        connect_args={"timeout": busy_timeout_ms / 1000.0, "check_same_thread": False},
        **codec,
    )

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection: Any, _record: Any) -> None:
        # Let us emit BEGIN ourselves (pysqlite would otherwise BEGIN lazily and DEFERRED).
        dbapi_connection.isolation_level = None
        cursor = dbapi_connection.cursor()
        try:
            cursor.execute("PRAGMA journal_mode=WAL")
            cursor.execute(f"PRAGMA busy_timeout={int(busy_timeout_ms)}")
            cursor.execute("PRAGMA foreign_keys=ON")
            cursor.execute("PRAGMA synchronous=NORMAL")
        finally:
            cursor.close()

    @event.listens_for(engine, "begin")
    def _on_begin(connection: Any) -> None:
        if connection.get_execution_options().get(_WRITE_OPTION):
            connection.exec_driver_sql("BEGIN IMMEDIATE")
        else:
            connection.exec_driver_sql("BEGIN")

    return engine


class Database:
    """An engine plus read and write session factories."""

    def __init__(self, url: str, *, busy_timeout_ms: int = 30_000) -> None:
        self.url = url
        self.engine = create_db_engine(url, busy_timeout_ms=busy_timeout_ms)
        self._read = sessionmaker(bind=self.engine, expire_on_commit=False)
        self._write = sessionmaker(
            bind=self.engine.execution_options(**{_WRITE_OPTION: True}), expire_on_commit=False
        )

    @contextmanager
    def read(self) -> Iterator[Session]:
        """A session for reads; closing it ends its transaction (objects stay loaded)."""
        with self._read() as session:
            yield session

    @contextmanager
    def write(self) -> Iterator[Session]:
        """A session whose transaction starts with ``BEGIN IMMEDIATE`` on SQLite.

        On PostgreSQL it is an ordinary READ COMMITTED transaction (see the module's notes).

        Commits when the block ends normally, rolls back on an exception.
        """
        with self._write() as session, session.begin():
            yield session

    def dispose(self) -> None:
        self.engine.dispose()
