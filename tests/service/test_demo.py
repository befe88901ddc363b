"""``regtree demo`` runs the bundled collection through the real service and exits 0."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from tests.service.conftest import REPO


def test_demo_end_to_end(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("REGTREE_")}
    env.update(PYTHONPATH=str(REPO), REGTREE_LOG_LEVEL="WARNING")
    done = subprocess.run(
        [sys.executable, "-m", "service.cli", "demo"],
        cwd=tmp_path,  # a fresh directory: the default database goes to ./var
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "succeeded" in done.stdout
    assert "layer >= 3" in done.stdout and "direct" in done.stdout
    assert (tmp_path / "var" / "regtree.sqlite").is_file()
