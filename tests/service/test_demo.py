"""``regtree demo`` runs the bundled collection through the real service and exits 0, showing
its progress and result and nothing of the server's logs."""

from __future__ import annotations

import io
import os
import re
import subprocess
import sys
from pathlib import Path

import httpx

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


def test_demo_run_twice_reuses_its_collection(client: httpx.Client) -> None:
    """A second run finds the collection and shapes of the first (by name) and stores
    nothing new; a shape missing from it is uploaded again."""
    from service.demo_run import _all, _demo_collection, load_demo_shapes

    name, shapes = load_demo_shapes()
    title = f"demo: {name}"
    first, first_shapes = _demo_collection(client, title, shapes, io.StringIO())
    second, second_shapes = _demo_collection(client, title, shapes, io.StringIO())
    assert second["id"] == first["id"]
    assert [s["id"] for s in second_shapes] == [s["id"] for s in first_shapes]
    assert [s["name"] for s in first_shapes] == list(shapes)
    assert [c["name"] for c in _all(client, "/v1/collections")].count(title) == 1
    url = f"/v1/collections/{first['id']}/shapes"
    assert len(_all(client, url)) == len(shapes)

    gone = first_shapes[1]
    assert client.delete(f"{url}/{gone['id']}").status_code == 204
    _, third_shapes = _demo_collection(client, title, shapes, io.StringIO())
    assert third_shapes[1]["name"] == gone["name"] and third_shapes[1]["id"] != gone["id"]
    assert [s["id"] for i, s in enumerate(third_shapes) if i != 1] == [
        s["id"] for i, s in enumerate(first_shapes) if i != 1
    ]
