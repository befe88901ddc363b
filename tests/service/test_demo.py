"""``regtree demo`` runs the bundled collection through the real service and exits 0, showing
its progress and result and nothing of the server's logs."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

from tests.service.conftest import REPO


def test_demo_end_to_end(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("REGTREE_")}
    env.update(PYTHONPATH=str(REPO))  # no REGTREE_LOG_LEVEL: the demo is quiet by itself
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
    assert done.stderr == ""  # no access lines, no worker lines
    assert not any(line.startswith("{") for line in done.stdout.splitlines())
    overall = [int(p) for p in re.findall(r"; 15 subjects; overall (\d+)%", done.stdout)]
    assert overall and overall == sorted(overall) and overall[-1] == 100, done.stdout
    running = r"^\[\s*[\d.]+ s\] job \d+ running similarity \d+/\d+ pairs"
    assert re.search(running, done.stdout, re.M), done.stdout
    assert "layer >= 3" in done.stdout and "direct" in done.stdout
    assert (tmp_path / "var" / "regtree.sqlite").is_file()
