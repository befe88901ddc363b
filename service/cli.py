"""The ``regtree`` command line.

Server side: serve, worker, migrate, demo. Client side (over HTTP, see
:mod:`service.cli_client`): upload, run, watch, results, cancel, export, similarity.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

from service import cli_client
from service.contract.names import DEFAULT_METHOD, REGISTRATION_METHODS


def _single_threaded_blas() -> None:
    # Before numpy is imported: parallelism comes from processes, not BLAS threads.
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="regtree",
        description="Register shape collections through a dynamic tree (Du et al. 2016). "
        "Settings come from REGTREE_* environment variables.",
    )
    parser.add_argument(
        "--database-url", help="overrides REGTREE_DATABASE_URL (default sqlite:///./var/...)"
    )
    cli_client.add_connection_options(parser, suppress=False)
    sub = parser.add_subparsers(dest="command", required=True)

    serve = sub.add_parser("serve", help="run the API and embedded workers (migrates first)")
    serve.add_argument("--host", default="127.0.0.1")
    serve.add_argument("--port", type=int, default=8000)
    serve.add_argument(
        "--workers",
        type=int,
        default=None,
        help="embedded worker processes "
        "(default REGTREE_EMBEDDED_WORKERS); 0 = run `regtree worker` separately",
    )
    serve.add_argument("--no-migrate", action="store_true", help="do not apply migrations")

    worker = sub.add_parser("worker", help="run a worker process")
    worker.add_argument("--burst", action="store_true", help="exit when the queue is empty")

    mig = sub.add_parser("migrate", help="apply or revert database migrations")
    mig.add_argument(
        "action", nargs="?", default="upgrade", choices=["upgrade", "downgrade", "current"]
    )
    mig.add_argument("revision", nargs="?", help="target revision (upgrade: head; downgrade: -1)")

    demo = sub.add_parser("demo", help="register the bundled demo collection end to end")
    demo.add_argument("--workers", type=int, default=1)
    demo.add_argument("--method", default=DEFAULT_METHOD, choices=REGISTRATION_METHODS)

    cli_client.add_commands(sub)
    return parser


#: The extra (pyproject.toml) that installs each optional top-level module a command imports.
EXTRA_OF = {
    "httpx": "client",
    "pydantic": "client",
    "fastapi": "server",
    "starlette": "server",
    "uvicorn": "server",
    "sqlalchemy": "server",
    "alembic": "server",
    "pydantic_settings": "server",
    "multipart": "server",
    "matplotlib": "plots",
    "PIL": "images",
    "skimage": "images",
    "psycopg": "postgres",
}


def main(argv: Sequence[str] | None = None) -> int:
    """Run a command; a part of the install it needs that is missing is a usage error (2)
    naming the extra to install."""
    argv = cli_client.join_option_values(sys.argv[1:] if argv is None else argv)
    args = _parser().parse_args(argv)
    try:
        return _run(args)
    except ModuleNotFoundError as e:
        module = (e.name or "").split(".")[0]
        if module not in EXTRA_OF:
            raise
        # the server's commands need all of the server extra, whichever module was first
        extra = EXTRA_OF[module] if args.command in cli_client.COMMANDS else "server"
        print(
            f"regtree: this command needs {module}, which is not installed: "
            f"pip install 'regtree[{extra}]' (in a checkout: pip install -e '.[{extra}]')",
            file=sys.stderr,
        )
        return 2


def _run(args: argparse.Namespace) -> int:
    if args.command in cli_client.COMMANDS:
        return cli_client.main(args)
    if args.command in ("serve", "worker", "demo"):
        _single_threaded_blas()

    from service.core.config import Settings
    from service.core.logging import configure_logging

    overrides = {"database_url": args.database_url} if args.database_url else {}
    settings = Settings(**overrides)
    if args.command == "demo" and "log_level" not in settings.model_fields_set:
        # the demo shows its progress and result; the server's and workers' INFO lines (each
        # poll, each job claimed) would bury them. REGTREE_LOG_LEVEL still brings them back.
        settings = settings.model_copy(update={"log_level": "WARNING"})
    configure_logging(settings.log_level, settings.log_style)

    if args.command == "serve":
        from service.embedded import serve

        workers = settings.embedded_workers if args.workers is None else args.workers
        serve(
            settings,
            host=args.host,
            port=args.port,
            workers=workers,
            migrate_db=not args.no_migrate,
        )
        return 0
    if args.command == "worker":
        from service.worker import Worker

        worker = Worker(settings)
        worker.install_signal_handlers()
        worker.run(burst=args.burst)
        return 0
    if args.command == "migrate":
        from service import migrate

        if args.action == "upgrade":
            migrate.upgrade(settings, args.revision or "head")
        elif args.action == "downgrade":
            migrate.downgrade(settings, args.revision or "-1")
        print(migrate.current_revision(settings) or "base")
        return 0
    if args.command == "demo":
        from service.demo_run import run_demo

        return run_demo(settings, workers=args.workers, method=args.method)
    return 2


if __name__ == "__main__":
    sys.exit(main())
