"""Service settings, read from the environment (prefix ``REGTREE_``) and an optional ``.env``.

Every limit that protects the service from a bad upload or a runaway job lives here, so an
operator can see and change them in one place.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any, Literal

from pydantic import Field, SecretStr, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from service.core.backoff import CALLBACK_BACKOFF, JOB_BACKOFF, Backoff


def _doubling_wait(default: Backoff, before: str, cap: str) -> Any:
    """A backoff's first setting: the wait before ``before``, doubling with each further
    attempt up to its second, the setting named ``cap`` (:func:`_longest_wait`)."""
    return Field(default=default.base, ge=0, description=f"Wait before {before}; it doubles "
                 f"with each further attempt, up to {cap}.")


def _longest_wait(default: Backoff) -> Any:
    """A backoff's second setting: the cap of its doubling wait."""
    return Field(default=default.cap, ge=0)


class Settings(BaseSettings):
    """Settings for the API, the workers and the CLI.

    Every field can be set with an environment variable named ``REGTREE_<FIELD>`` in upper
    case, e.g. ``REGTREE_DATABASE_URL`` or ``REGTREE_API_KEY``.
    """

    model_config = SettingsConfigDict(
        env_prefix="REGTREE_", env_file=".env", env_file_encoding="utf-8", extra="ignore"
    )

    # --- storage -------------------------------------------------------------------------
    database_url: str = "sqlite:///./var/regtree.sqlite"
    sqlite_busy_timeout_ms: int = Field(default=30_000, ge=0)
    migrations_dir: str | None = Field(
        default=None,
        description="Folder holding the Alembic env.py; found next to the package when unset.",
    )

    # --- security ------------------------------------------------------------------------
    api_key: SecretStr | None = Field(
        default=None,
        description="When set, every request except /healthz and the API docs must send it "
        "as `X-API-Key: <key>` or `Authorization: Bearer <key>`.",
    )

    # --- request limits --------------------------------------------------------------------
    # The OpenAPI document states the configured values (service.core.limits); a request past
    # one is refused with a problem document naming the setting, and stores nothing.
    max_body_bytes: int = Field(
        default=32 * 1024 * 1024, ge=1024, description="Request body size, in bytes (413)."
    )
    max_points_per_shape: int = Field(
        default=20_000,
        ge=3,
        description="Points in one shape, in an image's target_points and in one transform "
        "request.",
    )
    min_points: int = Field(default=3, ge=1, description="Points a shape needs at least.")
    max_shapes_per_collection: int = Field(default=2_000, ge=1)
    max_batch_files: int = Field(
        default=500, ge=1, description="Files (multipart) or shapes (JSON batch) in one upload."
    )
    max_coordinate: float = Field(
        default=1e7, gt=0, description="Largest absolute value of an uploaded coordinate."
    )
    max_image_pixels: int = Field(default=25_000_000, ge=1, description="Pixels of an image.")
    max_page_size: int = Field(
        default=500, ge=1, description="Items in one page of a list (`?limit=`); 50 by default."
    )

    # --- job queue -------------------------------------------------------------------------
    worker_lease_seconds: float = Field(default=60.0, gt=0)
    worker_heartbeat_seconds: float = Field(default=10.0, gt=0)
    worker_poll_seconds: float = Field(
        default=1.0,
        gt=0,
        description="How often an idle worker looks for due jobs (with jitter: 0.5-1x). A "
        "job queued through the API wakes an idle worker at once (on PostgreSQL any "
        "worker, by NOTIFY; on SQLite the workers `regtree serve` starts); the poll covers "
        "the rest (retries after their backoff, jobs whose worker was lost).",
    )
    cancel_poll_seconds: float = Field(
        default=1.0,
        gt=0,
        description="How often a worker running a job looks for a cancel request (a read) "
        "between heartbeats; a cancelled job stops within about this long.",
    )
    max_attempts: int = Field(
        default=3,
        ge=1,
        description="Attempts a job gets: a transient failure (database busy or locked, a "
        "worker that stopped responding) is retried until this many were used.",
    )
    retry_backoff_seconds: float = _doubling_wait(
        JOB_BACKOFF, "the first retry of a job after a transient failure",
        "retry_backoff_max_seconds",
    )
    retry_backoff_max_seconds: float = _longest_wait(JOB_BACKOFF)
    progress_min_interval_seconds: float = Field(default=0.5, ge=0)

    # --- callbacks (a job's callback_url, called when it ends) -----------------------------
    callback_secret: SecretStr | None = Field(
        default=None,
        description="Shared secret signing callbacks (X-Regtree-Signature: sha256=HMAC of "
        "'<X-Regtree-Timestamp>.<body>'). A job with callback_url is refused (422) without it.",
    )
    callback_allowed_hosts: str = Field(
        default="",
        description="Comma-separated hosts a callback_url may name: 'host', 'host:port' or "
        "'*.domain' (its subdomains). Empty: callbacks are refused (422).",
    )
    callback_max_attempts: int = Field(default=5, ge=1)
    callback_backoff_seconds: float = _doubling_wait(
        CALLBACK_BACKOFF, "the second delivery attempt of a callback",
        "callback_backoff_max_seconds",
    )
    callback_backoff_max_seconds: float = _longest_wait(CALLBACK_BACKOFF)
    callback_timeout_seconds: float = Field(default=10.0, gt=0)
    callback_poll_seconds: float = Field(default=1.0, gt=0)
    public_url: str | None = Field(
        default=None,
        description="The URL clients reach the API at (e.g. https://regtree.example.org): "
        "callback bodies give absolute job and result URLs with it, paths without.",
    )

    # --- workers ---------------------------------------------------------------------------
    embedded_workers: int = Field(default=1, ge=0)
    executor: Literal["serial", "process", "dask"] = Field(
        default="process",
        description="Where a job's heavy stages (ICP, CPD) run: `process`, a local process "
        "pool; `serial`, the worker's own thread; `dask`, the Dask distributed cluster at "
        "dask_scheduler (needs the `dask` extra).",
    )
    executor_processes: int | None = Field(default=None, ge=1)
    dask_scheduler: str | None = Field(
        default=None,
        description="Address of the Dask scheduler (e.g. tcp://scheduler:8786) for "
        "executor=dask.",
    )
    dask_connect_seconds: float = Field(
        default=30.0,
        gt=0,
        description="With executor=dask, how long a job's attempt waits to reach the scheduler "
        "before it fails.",
    )
    dask_no_worker_seconds: float = Field(
        default=60.0,
        gt=0,
        description="With executor=dask, a job fails when the cluster has had no worker for "
        "this long while its tasks wait.",
    )

    # --- logging ---------------------------------------------------------------------------
    log_level: str = "INFO"
    log_format: Literal["auto", "json", "text"] = Field(
        default="auto",
        description="Log lines on stderr: `text` (readable), `json` (one object per line), or "
        "`auto`: text on a terminal, JSON otherwise.",
    )
    log_json: bool | None = Field(
        default=None,
        description="Older switch, kept working: true = `json`, false = `text`; overrides "
        "log_format when set.",
    )

    @property
    def retry_backoff(self) -> Backoff:
        """The job queue's wait before retrying a job (retry_backoff_*)."""
        return Backoff(self.retry_backoff_seconds, self.retry_backoff_max_seconds)

    @property
    def callback_backoff(self) -> Backoff:
        """The wait before delivering a callback again (callback_backoff_*)."""
        return Backoff(self.callback_backoff_seconds, self.callback_backoff_max_seconds)

    @property
    def log_style(self) -> str:
        """The log format in force: ``log_json`` when set, else ``log_format``."""
        if self.log_json is not None:
            return "json" if self.log_json else "text"
        return self.log_format

    @model_validator(mode="after")
    def _consistent_limits(self) -> Settings:
        # Checked at start-up: otherwise every upload would fail (service.ingest.Limits).
        if self.min_points > self.max_points_per_shape:
            raise ValueError(
                f"min_points ({self.min_points}) must not exceed max_points_per_shape "
                f"({self.max_points_per_shape})"
            )
        if self.executor == "dask" and not self.dask_scheduler:
            raise ValueError(
                "executor=dask needs dask_scheduler (REGTREE_DASK_SCHEDULER), the address of "
                "the Dask scheduler, e.g. tcp://scheduler:8786"
            )
        return self


@lru_cache
def get_settings() -> Settings:
    """The process-wide settings, read once from the environment."""
    return Settings()
