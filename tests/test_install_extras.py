"""Install what you use (pyproject.toml's extras): each part runs with only its own
dependencies, checked in a fresh interpreter whose imports of everything else fail as if it
were not installed.

* the library (base install): only numpy and scipy besides the standard library;
* the client and the CLI's client commands (``[client]``): no server, picture or image
  package;
* a command that needs a missing extra says which one to install.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: Installed in a server's environment but not part of the client's install.
NOT_CLIENT = [
    "fastapi",
    "starlette",
    "uvicorn",
    "sqlalchemy",
    "alembic",
    "pydantic_settings",
    "multipart",
    "python_multipart",
    "matplotlib",
    "PIL",
    "skimage",
    "scipy",
    "pycpd",
    "psycopg",
]

BLOCKER = """
import sys

class Blocked:
    def __init__(self, allowed=None, blocked=()):
        self.allowed, self.blocked, self.refused = allowed, set(blocked), []

    def find_spec(self, name, path=None, target=None):
        top = name.partition(".")[0]
        if self.allowed is not None:
            ok = top in self.allowed or top in sys.stdlib_module_names or top.startswith("_")
        else:
            ok = top not in self.blocked
        if ok:
            return None
        self.refused.append(name)
        raise ModuleNotFoundError(f"blocked: {name}", name=name)
"""


def run(code: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run(
        [sys.executable, "-c", BLOCKER + textwrap.dedent(code)],
        capture_output=True,
        text=True,
        env=env,
        cwd=REPO,
        timeout=300,
    )


def test_the_library_needs_only_numpy_and_scipy() -> None:
    done = run(
        """
        blocker = Blocked(allowed={"numpy", "scipy", "registration"})
        sys.meta_path.insert(0, blocker)
        import numpy as np
        import registration
        from registration import build_dynamic_tree, cpd_nonrigid, register_direct
        from registration.synthetic import chained_family

        fam = chained_family(n_chains=1, chain_length=3, n_points=30, seed=0)
        plain = register_direct(fam.shapes, root=0, prealign=False)
        tree = build_dynamic_tree(fam.shapes, root=0)
        assert len(tree.to_dict()["subjects"]) == 3
        assert cpd_nonrigid(fam.shapes[0], fam.shapes[1]).warped.shape == fam.shapes[0].shape
        loaded = {m.partition(".")[0] for m in sys.modules}
        ours = {"numpy", "scipy", "registration", "cython_runtime"}  # Cython: scipy's
        extra = loaded - ours - set(sys.stdlib_module_names)
        print("refused", sorted(set(blocker.refused)))
        print("extra", sorted(m for m in extra if not m.startswith("_")))
        """
    )
    assert done.returncode == 0, done.stderr
    assert "extra []" in done.stdout, done.stdout


def test_the_client_and_its_cli_need_no_server_packages() -> None:
    done = run(
        f"""
        sys.meta_path.insert(0, Blocked(blocked={NOT_CLIENT!r}))
        from service.client import RegtreeClient, JobResult
        from service.progress import progress_text, Progress
        import service.cli_client
        from service.cli import main

        # a client command runs to its connection error: the whole client path imports
        code = main(["cancel", "1", "--url", "http://127.0.0.1:9", "--timeout", "2"])
        print("exit", code)
        assert not any(m.partition(".")[0] in {NOT_CLIENT!r} for m in sys.modules)
        """
    )
    assert done.returncode == 0, done.stderr
    assert "exit 3" in done.stdout, (done.stdout, done.stderr)
    assert "is the service running there?" in done.stderr


def test_a_command_without_its_extra_names_the_extra() -> None:
    done = run(
        """
        sys.meta_path.insert(0, Blocked(blocked={"fastapi", "sqlalchemy", "uvicorn"}))
        from service.cli import main

        print("exit", main(["migrate"]))
        """
    )
    assert done.returncode == 0, done.stderr
    assert "exit 2" in done.stdout
    assert "pip install 'regtree[server]'" in done.stderr, done.stderr
