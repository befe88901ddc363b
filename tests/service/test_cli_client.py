"""``regtree upload|run|watch|results|cancel`` as subprocesses against the real service.

Exit codes are the real ones: every command runs as ``python -m service.cli`` in its own
process, talking HTTP to ``regtree serve`` subprocesses from conftest.
"""

from __future__ import annotations

import io
import json
import os
import pty
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image, ImageDraw

from service.client import RegtreeClient
from tests.service.conftest import REPO, Service, free_port, insert_legacy_shape

CLI = [sys.executable, "-m", "service.cli"]


def cli_env(url: str | None = None, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("REGTREE_")}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
    if url is not None:
        env["REGTREE_URL"] = url
    env.update(extra)
    return env


def regtree(
    *args: str, url: str | None = None, env: dict[str, str] | None = None, timeout: float = 60
) -> subprocess.CompletedProcess[str]:
    """Run ``regtree ARGS`` (REGTREE_URL=url) and return the finished process."""
    return subprocess.run(
        [*CLI, *args],
        cwd=REPO,
        env=env or cli_env(url),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def assert_error(proc: subprocess.CompletedProcess[str], code: int, *needles: str) -> str:
    """Exit ``code``, one ``regtree: error:`` line on stderr holding every needle."""
    assert proc.returncode == code, (proc.returncode, proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.startswith("regtree: error:")]
    assert len(lines) == 1, proc.stderr
    for needle in needles:
        assert needle in lines[0], (needle, proc.stderr)
    return lines[0]


def write_folder(folder: Path) -> list[str]:
    """The chained family as .txt / .npy files plus an ellipse PNG; names in upload order."""
    from registration.synthetic import chained_family

    folder.mkdir()
    fam = chained_family(n_chains=2, chain_length=3, n_points=60)
    names = []
    for k, (name, pts) in enumerate(zip(fam.names, fam.shapes, strict=True)):
        stem = f"{k:02d}-{name}"
        if k % 2:
            np.save(folder / f"{stem}.npy", pts)
        else:
            (folder / f"{stem}.txt").write_text("\n".join(f"{x:.9f} {y:.9f}" for x, y in pts))
        names.append(stem)
    image = Image.new("L", (120, 90), 255)
    ImageDraw.Draw(image).ellipse((15, 15, 105, 75), fill=0)
    image.save(folder / "99-ellipse.png")
    names.append("99-ellipse")
    (folder / "notes.md").write_text("not a shape")
    return names


PROGRESS = re.compile(
    r"^\[\s*[\d.]+ s\] job (\d+) (\w+)"
    r"(?: (.+?) (\d+)/(\d+) (?:pairs|registrations|subjects) \(\d+%\))?"
    r"(?:; (\d+) subjects)?(?:; overall (\d+)%(?:, about [\d:]+ left)?)?$"
)


def overall_percentages(stdout: str) -> list[int]:
    """The overall percentage of each plain progress line that has one."""
    return [int(m[7]) for m in map(PROGRESS.match, stdout.splitlines()) if m and m[7]]


def progress_lines(stdout: str) -> list[tuple[str, str | None, int, int]]:
    """(status, stage, done, total) of each plain progress line."""
    out = []
    for line in stdout.splitlines():
        m = PROGRESS.match(line)
        if m:
            done, total = int(m[4] or 0), int(m[5] or 0)
            out.append((m[2], m[3], done, total))
    return out


def run_in_pty(args: list[str], env: dict[str, str], timeout: float = 30) -> tuple[int, str]:
    master, slave = pty.openpty()
    process = subprocess.Popen(args, cwd=REPO, env=env, stdin=slave, stdout=slave, stderr=slave)
    os.close(slave)
    chunks: list[bytes] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            chunk = os.read(master, 65536)
        except OSError:  # the child closed the terminal
            break
        if not chunk:
            break
        chunks.append(chunk)
    os.close(master)
    return process.wait(timeout), b"".join(chunks).decode()


# --- the whole path ------------------------------------------------------------------------


def test_upload_run_watch_results(service: Service, tmp_path: Path) -> None:
    url = service.base_url
    names = write_folder(tmp_path / "shapes")

    up = regtree(
        "upload", str(tmp_path / "shapes"), "--collection", "cli-fam", "--create",
        "--batch-size", "3", "--target-points", "80", url=url,
    )  # fmt: skip
    assert up.returncode == 0, up.stderr
    assert re.findall(r"^batch (\d+): (\d+)/(\d+) files", up.stdout, re.M) == [
        ("1", "3", "8"),
        ("2", "6", "8"),
        ("3", "8", "8"),
    ]
    final = re.search(r"uploaded 8 shape\(s\) to collection 'cli-fam' \(id (\d+)\)", up.stdout)
    assert final, up.stdout
    collection_id = int(final[1])
    with RegtreeClient(url) as rt:
        assert [s.name for s in rt.list_shapes(collection_id)] == names

    again = regtree(
        "upload", str(tmp_path / "shapes"), "--collection", "cli-fam", "--create", url=url
    )
    assert_error(again, 1, "exists already", f"id {collection_id}")

    # --wait, stdout not a terminal: one plain line per change, done counts going up
    run = regtree(
        "run", "--collection", "cli-fam", "--model", "00-root", "--wait", "--poll", "0.05", url=url
    )
    assert run.returncode == 0, (run.stdout, run.stderr)
    job_id = int(re.search(r"^job (\d+) queued", run.stdout, re.M)[1])  # type: ignore[index]
    assert "\r" not in run.stdout and "\x1b" not in run.stdout
    lines = progress_lines(run.stdout)
    assert lines[0][0] in ("queued", "running") and lines[-1][0] == "succeeded"
    running = [(stage, done, total) for status, stage, done, total in lines if stage]
    by_stage: dict[str, list[int]] = {}
    for stage, done, _ in running:
        by_stage.setdefault(stage, []).append(done)
    assert all(v == sorted(v) for v in by_stage.values()), by_stage
    assert len({d for v in by_stage.values() for d in v}) >= 3, run.stdout  # it moved
    # the overall percentage never goes back and ends at 100; the subjects are counted right
    overall = overall_percentages(run.stdout)
    assert overall == sorted(overall) and overall[-1] == 100, run.stdout
    assert re.search(r"; 7 subjects; overall 100%$", run.stdout, re.M), run.stdout
    assert re.search(
        rf"^job {job_id} succeeded after [\d.]+ s: \d+ of 7 subjects", run.stdout, re.M
    )

    # on a terminal: one line redrawn with a bar
    code, screen = run_in_pty([*CLI, "watch", str(job_id)], cli_env(url))
    assert code == 0, screen
    assert "\r\x1b[K" in screen and re.search(r"7 subjects .* \[#+\]\s+100%", screen), screen
    assert f"job {job_id} succeeded" in screen

    out = tmp_path / "out"
    res = regtree("results", str(job_id), "--out", str(out), url=url)
    assert res.returncode == 0, res.stderr
    doc = json.loads((out / "result.json").read_text())
    assert doc["job_id"] == job_id
    assert sorted(s["name"] for s in doc["subjects"]) == sorted(names[1:])
    assert all("warped" in s for s in doc["subjects"] if s["attached"])  # the full document
    svg = (out / "tree.svg").read_text()
    assert svg.lstrip().startswith(("<?xml", "<svg"))
    for name in names:
        assert name in svg, name
    for png in ["tree.png", "summary.png", *(f"subjects/{n}.png" for n in names[1:])]:
        with Image.open(out / png) as picture:
            picture.load()
            assert picture.format == "PNG"
            assert 200 <= picture.width <= 6000 and 150 <= picture.height <= 6000, png
            assert len(np.unique(np.asarray(picture.convert("L")))) > 10, png  # not blank
    assert not (out / "subjects" / "00-root.png").exists()
    attached = sum(1 for s in doc["subjects"] if s["attached"])
    table = res.stdout
    assert re.search(
        r"^\s*layer >= 3\s+\d+\s+[\d.e-]+\s+[\d.e-]+\s+[\d.e-]+\s+[\d.e-]+$", table, re.M
    )
    assert re.search(rf"^\s*all attached\s+{attached}\s", table, re.M)
    for layer, stats in doc["summary"]["per_layer"].items():
        count = sum(1 for s in doc["subjects"] if s["layer"] == int(layer))
        assert re.search(rf"^\s+{layer}\s+{count}\s+", table, re.M), (layer, stats, table)
    for path in ("result.json", "tree.svg", "tree.png", "summary.png"):
        assert f"wrote {out / path}" in table
    assert f"wrote {len(names) - 1} subject picture(s)" in table

    # each subject drawn as the service draws it: the PNG upload (pixel coordinates) with y
    # downwards, the coordinate files upwards; --y-down draws them all downwards
    def pixels(data: bytes) -> np.ndarray:
        with Image.open(io.BytesIO(data)) as picture:
            return np.asarray(picture.convert("L"))

    ids = {s["name"]: s["shape_id"] for s in doc["subjects"]}
    down = tmp_path / "down"
    flipped = regtree("results", str(job_id), "--out", str(down), "--y-down", url=url)
    assert flipped.returncode == 0, flipped.stderr
    with httpx.Client(base_url=url) as http:
        for name in ("01-chain1-step1", "02-chain1-step2", "99-ellipse"):
            served = http.get(f"/v1/jobs/{job_id}/result/subjects/{ids[name]}/overlay.png")
            assert served.status_code == 200, served.text
            ours = (out / "subjects" / f"{name}.png").read_bytes()
            assert np.array_equal(pixels(ours), pixels(served.content)), name
            same = np.array_equal(pixels((down / "subjects" / f"{name}.png").read_bytes()),
                                  pixels(ours))
            assert same == (name == "99-ellipse"), name

    svg_out = tmp_path / "svg"
    some = regtree(
        "results", str(job_id), "--out", str(svg_out), "--subjects", "attached", "--format", "svg",
        url=url,
    )  # fmt: skip
    assert some.returncode == 0, some.stderr
    drawn = sorted(p.stem for p in (svg_out / "subjects").iterdir())
    assert drawn == sorted(s["name"] for s in doc["subjects"] if s["attached"])
    assert all(p.read_text().count("<svg") == 1 for p in (svg_out / "subjects").iterdir())


# --- failures ------------------------------------------------------------------------------


def test_failures_exit_codes(service: Service, tmp_path: Path) -> None:
    url = service.base_url
    assert_error(regtree("watch", "987654", url=url), 1, "Not Found", "987654", "HTTP 404")
    assert_error(regtree("results", "987654", "--out", str(tmp_path), url=url), 1, "HTTP 404")

    # unreachable: exit 3, naming the URL
    dead = f"http://127.0.0.1:{free_port()}"
    assert_error(regtree("--url", dead, "watch", "1"), 3, dead)
    assert_error(regtree("watch", "1", url=dead), 3, dead)  # from REGTREE_URL

    # usage: exit 2 (argparse, and what the CLI checks before asking the service)
    for args in (
        ["watch", "abc"],
        ["results", "1", "--sort", "name"],
        ["results", "1", "--min-confidence", "1.5"],
        ["run", "--collection", "c", "--model", "m", "--method", "nope"],
        ["run", "--collection", "c", "--model", "m", "--similarity-threshold", "-1"],
        ["upload", str(tmp_path), "--collection", "c", "--target-points", "0"],
        ["frobnicate"],
    ):
        proc = regtree(*args, url=url)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, (args, proc.stderr)
    assert_error(regtree("upload", str(tmp_path / "missing"), "--collection", "c", url=url), 2)
    assert_error(regtree("upload", str(tmp_path), "--collection", "c", url=url), 2, "no shape")
    assert_error(regtree("--url", "ftp://host", "watch", "1"), 2, "--url")

    with RegtreeClient(url) as rt:
        twins = [rt.create_collection("twin") for _ in range(2)]
        for twin in twins:
            rt.upload_points(twin.id, "a", np.c_[np.cos(np.arange(9)), np.sin(np.arange(9))])
        bad = rt.create_collection("degenerate")
        # refused at upload now; a database from before may hold one
        dot = insert_legacy_shape(service, bad.id, "dot", np.zeros((6, 2)))
        rt.upload_points(bad.id, "ring", np.c_[np.cos(np.arange(9)), np.sin(np.arange(9))])
    assert_error(
        regtree("run", "--collection", "twin", "--model", "a", url=url),
        2,
        "ambiguous",
        f"id {twins[0].id}",
        f"id {twins[1].id}",
    )
    assert_error(
        regtree("run", "--collection", str(twins[1].id), "--model", "zz", url=url),
        1,
        "no shape named 'zz'",
    )
    assert_error(regtree("run", "--collection", "nope", "--model", "a", url=url), 1, "nope")
    (tmp_path / "one").mkdir()
    (tmp_path / "one" / "a.txt").write_text("0 0\n1 0\n0 1\n")
    missing = regtree("upload", str(tmp_path / "one"), "--collection", "nope", url=url)
    assert_error(missing, 1, "no collection named 'nope'")
    # a folder with several broken files: every one named in the one error line, nothing of
    # that batch stored, and none of the Python client's wording
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "a-two.txt").write_text("0 0\n1 1\n")
    (tmp_path / "broken" / "b-ok.txt").write_text("0 0\n1 0\n0 1\n")
    (tmp_path / "broken" / "c-nan.txt").write_text("0 0\n1 nan\n0 1\n")
    refused = regtree("upload", str(tmp_path / "broken"), "--collection", "broken", "--create",
                      url=url)
    line = assert_error(refused, 1, "a-two.txt: got 2 points", "1 more of the 3 files",
                        "c-nan.txt: ", "nothing of the refused batch was stored",
                        "keeps the 0 shape(s)")
    assert "exc." not in line, line

    # a job that fails on the worker: exit 1 with the server's error
    run = regtree("run", "--collection", "degenerate", "--model", "dot", "--wait", url=url)
    job_id = int(re.search(r"^job (\d+) ", run.stdout, re.M)[1])  # type: ignore[index]
    with RegtreeClient(url) as rt:
        error = rt.get_job(job_id).error
    assert error, "the degenerate job should fail"
    assert f"shape {dot} 'dot' has zero size" in error, error  # its id and name, not shapes[k]
    assert_error(run, 1, f"job {job_id} failed", error)
    assert re.search(rf"^job {job_id} failed", run.stdout, re.M)
    assert_error(regtree("watch", str(job_id), url=url), 1, error)
    assert_error(regtree("results", str(job_id), "--out", str(tmp_path), url=url), 1, "HTTP 409")


def test_run_pose(service: Service, tmp_path: Path) -> None:
    from service.cli import _parser

    parse = _parser().parse_args
    base = ["run", "--collection", "c", "--model", "m"]
    # Nothing sent unless given: the service's default applies, as for any HTTP client.
    assert (parse(base).pose, parse(base).max_rotation) == (None, None)
    assert parse([*base, "--pose", "as_given"]).pose == "as_given"
    with pytest.raises(SystemExit) as usage:
        parse([*base, "--pose", "sideways"])
    assert usage.value.code == 2

    url = service.base_url
    for name, width in (("a", 90), ("b", 80)):
        image = Image.new("L", (width, 70), 255)
        ImageDraw.Draw(image).ellipse((10, 12, width - 10, 58), fill=0)
        image.save(tmp_path / f"{name}.png")
    with RegtreeClient(url) as rt:
        scans = rt.create_collection("cli-pose-scans")
        rt.upload_files(scans.id, [tmp_path / "a.png", tmp_path / "b.png"], target_points=30)
        points = rt.create_collection("cli-pose-points")
        for k in (1.0, 2.0):
            ring = np.c_[np.cos(np.arange(20)), k * np.sin(np.arange(20))]
            rt.upload_points(points.id, f"s{k:g}", ring)

    default = regtree("run", "--collection", "cli-pose-scans", "--model", "a", url=url)
    assert default.returncode == 0, default.stderr
    assert "pose upright +-30 deg (default for image collections)" in default.stdout
    given = regtree(
        "run", "--collection", "cli-pose-points", "--model", "s1", "--method", "direct",
        "--pose", "affine", "-q", url=url,
    )  # fmt: skip
    assert given.returncode == 0, given.stderr
    with RegtreeClient(url) as rt:
        params = rt.wait(int(given.stdout.strip()), timeout=60).params
    assert [params["pose"], params["max_rotation"], params["pose_source"]] == [
        "affine", None, "request",
    ]  # fmt: skip
    wrong = regtree(
        "run", "--collection", "cli-pose-points", "--model", "s1", "--pose", "rotation",
        "--max-rotation", "10", url=url,
    )  # fmt: skip
    assert_error(wrong, 1, "HTTP 422", "max_rotation")


def test_interrupt_cancel_and_api_key(make_service: Callable[..., Service]) -> None:
    svc = make_service(workers=0, env={"REGTREE_API_KEY": "k3y"}).start()  # jobs stay queued
    url = svc.base_url
    denied = regtree("run", "--collection", "c", "--model", "a", url=url)
    assert_error(denied, 1, "Unauthorized", "HTTP 401", "--api-key")
    keyed = cli_env(url, REGTREE_API_KEY="k3y")
    with RegtreeClient(url, api_key="k3y") as rt:
        coll = rt.create_collection("queued")
        for k in (1.0, 2.0):
            rt.upload_points(
                coll.id, f"s{k:g}", np.c_[np.cos(np.arange(20)), k * np.sin(np.arange(20))]
            )

    # connection options before or after the command name; none from the environment
    run = regtree(
        "--api-key", "k3y", "run", "--collection", "queued", "--model", "s1", "-q", "--url", url,
        env=cli_env(),
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    job_id = int(run.stdout.strip())

    def interrupted(*extra: str) -> subprocess.CompletedProcess[str]:
        process = subprocess.Popen(
            [*CLI, "watch", str(job_id), "--poll", "0.1", *extra],
            cwd=REPO,
            env=keyed,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            # a shell's background jobs ignore SIGINT, and children inherit that
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )
        assert process.stdout is not None
        first = process.stdout.readline()
        assert f"job {job_id} queued" in first, first
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=30)
        return subprocess.CompletedProcess(process.args, process.returncode, first + stdout, stderr)

    left = interrupted()
    assert_error(left, 130, "interrupted", "keeps running", f"regtree watch {job_id}")
    with RegtreeClient(url, api_key="k3y") as rt:
        assert rt.get_job(job_id).status == "queued"

    stopped = interrupted("--cancel-on-interrupt")
    assert_error(stopped, 130, "cancel requested")
    with RegtreeClient(url, api_key="k3y") as rt:
        assert rt.get_job(job_id).status == "cancelled"
    assert_error(regtree("watch", str(job_id), env=keyed), 1, f"job {job_id} cancelled")
    assert_error(regtree("cancel", str(job_id), env=keyed), 1, "HTTP 409")


def test_connection_options_before_or_after_the_command() -> None:
    from service.cli import _parser

    parse = _parser().parse_args
    default = parse(["watch", "3"])
    assert (default.url, default.api_key, default.timeout, default.job) == (None, None, 60.0, 3)
    before = parse(["--url", "http://a:1", "--api-key", "k", "--timeout", "5", "watch", "3"])
    after = parse(["watch", "3", "--url", "http://a:1", "--api-key", "k", "--timeout", "5"])
    for args in (before, after):
        assert (args.url, args.api_key, args.timeout) == ("http://a:1", "k", 5.0)
    serve = parse(["serve", "--port", "9000"])  # the server commands are unchanged
    assert (serve.command, serve.port, serve.workers, serve.host) == (
        "serve",
        9000,
        None,
        "127.0.0.1",
    )
    results = parse(["results", "#7", "--out", "d", "--subjects", "3"])
    assert (results.job, results.subjects, results.format) == (7, 3, "png")


# --- the results tables, by method --------------------------------------------------------


def _doc(method: str, direct: bool) -> dict[str, object]:
    subjects = [
        {"shape_id": 2, "name": "b", "layer": 2, "parent_shape_id": 1, "error": 0.002,
         "direct_error": 0.003 if direct else None, "confidence": 0.9, "attached": True},
        {"shape_id": 3, "name": "c", "layer": 3 if method != "direct" else 2,
         "parent_shape_id": 2 if method != "direct" else 1, "error": 0.004,
         "direct_error": 0.005 if direct else None, "confidence": 0.8, "attached": True},
    ]  # fmt: skip
    per = {"count": 1, "mean": 0.004, "p95": 0.004}
    summary: dict[str, object] = {"depth": 3, "layer_ge_3": per, "all": per}
    if direct:
        summary["direct"] = {"layer_ge_3": per, "all": per}
    return {"job_id": 7, "method": method, "root_shape_id": 1, "shape_ids": [1, 2, 3],
            "names": ["a", "b", "c"], "summary": summary, "subjects": subjects}  # fmt: skip


@pytest.mark.parametrize(
    ("method", "direct", "own", "compared"),
    [
        ("dynamic_tree", True, "tree", True),
        ("dynamic_tree", False, "tree", False),
        ("static_tree", False, "static", False),
        ("direct", False, "direct", None),
    ],
)
def test_results_tables_name_the_method_and_compare_only_a_tree(
    method: str, direct: bool, own: str, compared: bool | None
) -> None:
    # a direct job's e is direct CPD's: no "tree" columns, no comparison, no note about one
    from service.cli_client import subjects_table, summary_table

    doc = _doc(method, direct)
    summary = "\n".join(summary_table(doc))
    assert re.search(rf"^\s+layer\s+subjects\s+{own} mean\s+{own} p95", summary, re.M), summary
    if own != "tree":
        assert "tree mean" not in summary
    header = next(line for line in summary.splitlines() if "subjects" in line.split())
    note = "direct CPD was not compared"
    if compared is None:  # the direct job itself: its own columns only
        assert header.split()[2:] == ["direct", "mean", "direct", "p95"], header
        assert note not in summary, summary
    else:
        assert header.split()[2:] == [own, "mean", own, "p95", "direct", "mean", "direct", "p95"]
        assert (note in summary) != compared, summary
    table = subjects_table(doc, doc["subjects"])  # type: ignore[arg-type]
    assert ("direct e" in table[0]) == (compared is not None), table[0]
    assert len(table[1].split()) == (9 if compared is not None else 8), table
