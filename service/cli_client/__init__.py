"""The client-side ``regtree`` commands: drive a running service from a shell.

::

    regtree upload glyphs/ --collection yong --create --pattern '*.png' --target-points 300
    regtree run --collection yong --model 00-root --wait
    regtree watch 12
    regtree results 12 --out results/yong
    regtree results 12 --sort=-confidence --min-confidence 0.5
    regtree cancel 12
    regtree results 12 --csv > yong.csv
    regtree export 12 --out yong.zip
    regtree similarity 12 --k 3

They talk HTTP through :class:`service.client.RegtreeClient`: ``--url`` (default
``$REGTREE_URL``, else ``http://127.0.0.1:8000``), ``--api-key`` (default
``$REGTREE_API_KEY``) and ``--timeout`` (seconds per request) go before or after the
command name.

Exit codes: 0 success; 1 the service refused the request or the job failed / was cancelled
(the server's explanation on stderr); 2 usage errors (bad arguments, a missing folder, an
ambiguous name); 3 the service could not be reached (the URL is named); 130 interrupted by
Ctrl-C (a job keeps running on the server unless ``--cancel-on-interrupt``). Expected errors
are one ``regtree: error: ...`` line on stderr, never a traceback.

The package (by section: parser, _common, watch, results) imports only :mod:`argparse` and
:mod:`service.contract.names` (the standard library's typing) at import time: ``regtree
serve`` builds the same parser and must be able to limit BLAS threads before numpy is
imported.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING

from service.cli_client._common import (
    COMMANDS,
    DEFAULT_URL,
    CLIError,
    Exit,
    _check_url,
    _fail,
    describe_error,
)
from service.cli_client.group import cmd_group
from service.cli_client.parser import (
    add_commands,
    add_connection_options,
    join_option_values,
)
from service.cli_client.results import (
    cmd_export,
    cmd_results,
    cmd_similarity,
    subjects_table,
    summary_table,
)
from service.cli_client.watch import Progress, cmd_cancel, cmd_run, cmd_upload, cmd_watch
from service.contract.names import (
    IMAGE_MODES,
    METHODS,
    POSES,
    SUBJECT_SORTS,
    subject_status,
)

if TYPE_CHECKING:
    from service.client import RegtreeClient

__all__ = [
    "COMMANDS",
    "DEFAULT_URL",
    "HANDLERS",
    "IMAGE_MODES",
    "METHODS",
    "POSES",
    "SUBJECT_SORTS",
    "CLIError",
    "Exit",
    "Progress",
    "add_commands",
    "add_connection_options",
    "join_option_values",
    "main",
    "subject_status",
    "subjects_table",
    "summary_table",
]


HANDLERS: dict[str, Callable[[argparse.Namespace, RegtreeClient], int]] = {
    "upload": cmd_upload,
    "run": cmd_run,
    "watch": cmd_watch,
    "results": cmd_results,
    "cancel": cmd_cancel,
    "export": cmd_export,
    "similarity": cmd_similarity,
    "group": cmd_group,
}


# --- running -----------------------------------------------------------------------------


def main(args: argparse.Namespace) -> int:
    """Run a client command; return the exit code. Expected errors never raise."""
    from service.client import (
        JobFailed,
        RegtreeClient,
        RegtreeConnectionError,
        RegtreeError,
        RegtreeTimeout,
        Unauthorized,
    )

    url = (args.url or os.environ.get("REGTREE_URL") or DEFAULT_URL).strip()
    api_key = args.api_key if args.api_key is not None else os.environ.get("REGTREE_API_KEY")
    try:
        _check_url(url)
        with RegtreeClient(url, api_key=api_key or None, timeout=args.timeout) as rt:
            return int(HANDLERS[args.command](args, rt))
    except CLIError as e:
        return _fail(str(e), e.code)
    except KeyboardInterrupt:
        return _fail("interrupted", Exit.INTERRUPTED)
    except BrokenPipeError:  # e.g. `regtree results ... | head`: stop quietly
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return Exit.FAILED
    except RegtreeConnectionError as e:
        return _fail(
            f"{e} (is the service running there? set --url or REGTREE_URL)", Exit.CONNECTION
        )
    except RegtreeTimeout as e:
        return _fail(f"{e} [service at {url}]", Exit.CONNECTION)
    except JobFailed as e:
        return _fail(str(e), Exit.FAILED)
    except RegtreeError as e:
        message = describe_error(e)
        if isinstance(e, Unauthorized):
            message += " (give the key with --api-key or REGTREE_API_KEY)"
        return _fail(message, Exit.FAILED)
    except Exception as e:
        import httpx

        if isinstance(e, httpx.HTTPError):  # e.g. a scheme httpx does not speak
            return _fail(f"cannot talk to {url}: {e}", Exit.CONNECTION)
        raise


