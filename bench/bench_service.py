"""Time a whole service round trip on the 永 glyph edge set: upload, queue, every stage, result.

Starts ``regtree serve`` on a free port with a temporary SQLite file and two embedded workers
(or uses a running service given with ``--url``), uploads the 73 edge point sets of
``../shared/data/glyphs_yong/points/*_edge.txt`` through :class:`service.client.RegtreeClient`
(multipart batches, as a user's ``regtree upload`` would), runs one dynamic-tree job with
``compare_direct``, follows its progress, and prints how long each stage took (as the job
reports its stages: ``similarity round 1``, ``round 1``, ``similarity round 2``, ...,
``similarity direct``, ``direct``) and the job's summary: attached subjects, tree depth, and
mean / p95 of e on the subjects at layer >= 3, tree vs direct CPD.

The data folder sits beside the project and is not in a fresh clone: when it is missing the
script says so and exits 0, or, with ``--allow-generated``, runs on a generated chained
family instead. ``--points N`` resamples every shape to at most N points on the client side
before uploading (the service stores what it gets); by default the files go up as they are.

    .venv/bin/python bench/bench_service.py [--points 400] [--url http://127.0.0.1:8000]
        [--workers 2] [--allow-generated] [--model NAME] [--timeout 3600] [--repeat 3]

Stage times come from polling the job (``--poll`` seconds apart, and the server writes
progress at most every 0.1 s when this script starts it), so each is accurate to about one
poll interval, and a stage shorter than that may not be seen at all (its time then counts in
the stage before it); the queued wait uses the server's own ``created_at`` / ``started_at``.
Before the jobs and after them the script times a fixed numpy workload in its own process
(``machine reference``, the lesser of the two in the table; no change to the library moves
it), so that runs on different days can be told apart by the machine's speed; the first
can read high while the service's worker processes are still starting.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from registration import compiled_simd, resample  # noqa: E402
from service.client import JobStatus, RegtreeClient  # noqa: E402

DATA = REPO.parent / "shared" / "data"
EDGES = DATA / "glyphs_yong" / "points"


# --- the service ---------------------------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


@contextmanager
def local_service(workers: int, workdir: Path) -> Iterator[str]:
    """``regtree serve`` on a free port over a fresh SQLite file; yields its base URL."""
    port = _free_port()
    env = {
        **os.environ,
        "REGTREE_DATABASE_URL": f"sqlite:///{workdir / 'bench.sqlite'}",
        "REGTREE_PROGRESS_MIN_INTERVAL_SECONDS": "0.1",
        "REGTREE_LOG_LEVEL": "WARNING",
        "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])),
    }
    env.pop("REGTREE_API_KEY", None)
    log = (workdir / "server.log").open("wb")
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "service.cli",
            "serve",
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--workers",
            str(workers),
        ],
        cwd=workdir,
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while True:
            if process.poll() is not None:
                raise RuntimeError(
                    f"regtree serve exited with {process.returncode}; see {log.name}"
                )
            try:
                if httpx.get(f"{url}/healthz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"regtree serve did not start; see {log.name}")
            time.sleep(0.1)
        yield url
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(5)
        log.close()


# --- data --------------------------------------------------------------------------------


def load_edges(points: int | None) -> list[tuple[str, np.ndarray]]:
    shapes = []
    for path in sorted(EDGES.glob("*_edge.txt")):
        pts = np.loadtxt(path, dtype=np.float64).reshape(-1, 2)
        shapes.append((path.name.removesuffix(".txt"), pts))
    return _resampled(shapes, points)


def generated(points: int | None) -> list[tuple[str, np.ndarray]]:
    from registration.synthetic import chained_family

    fam = chained_family(n_chains=4, chain_length=6, n_points=points or 400, seed=0)
    return list(zip(fam.names, fam.shapes, strict=True))


def _resampled(
    shapes: list[tuple[str, np.ndarray]], points: int | None
) -> list[tuple[str, np.ndarray]]:
    if points is None:
        return shapes
    return [(name, resample(pts, points)) for name, pts in shapes]


def write_point_files(shapes: list[tuple[str, np.ndarray]], folder: Path) -> list[Path]:
    """The shapes as ``.txt`` point files, the form a user uploads (prepared before timing)."""
    paths = []
    for name, pts in shapes:
        path = folder / f"{name}.txt"
        np.savetxt(path, pts, fmt="%.6g")
        paths.append(path)
    return paths


# --- timing ------------------------------------------------------------------------------


@dataclass
class StageTimes:
    """First and last time (monotonic) each progress stage was seen, in order."""

    order: list[str] = field(default_factory=list)
    first: dict[str, float] = field(default_factory=dict)
    last: dict[str, float] = field(default_factory=dict)
    total: dict[str, int] = field(default_factory=dict)
    running_at: float | None = None
    finished_at: float | None = None

    def see(self, state: JobStatus) -> None:
        now = time.monotonic()
        if state.status == "running" and self.running_at is None:
            self.running_at = now
        if state.finished and self.finished_at is None:
            self.finished_at = now
        if state.stage is None or state.finished:
            return
        if state.stage not in self.first:
            self.order.append(state.stage)
            self.first[state.stage] = now
        self.last[state.stage] = now
        self.total[state.stage] = state.total

    def rows(self) -> list[tuple[str, float, int]]:
        """(stage, seconds, items): a stage lasts until the next one is first seen."""
        out = []
        for i, stage in enumerate(self.order):
            if i + 1 < len(self.order):
                end = self.first[self.order[i + 1]]
            else:
                end = self.finished_at or self.last[stage]
            out.append((stage, end - self.first[stage], self.total.get(stage, 0)))
        return out


#: The machine reference's workload (`machine_reference`): this many Gaussian kernel
#: passes over all pairs of two fixed sets of this many points.
REFERENCE_POINTS = 400
REFERENCE_ITERATIONS = 20


def machine_reference(repeats: int = 5) -> float:
    """Seconds for a fixed CPU workload like the job's, in this process, that no change to
    the library moves: numpy's Gaussian kernels of all pairs of two fixed 400-point sets,
    their column sums and the normalised row sums (a dense E-step's work, without BLAS),
    20 times; the least of `repeats` runs.

    The job's time on this 2-core machine moved by a third between sessions for the same
    code (bench/RESULTS.md 7.24-7.25); this figure, measured beside it (after the upload
    and after the jobs), tells a slower machine from a slower change."""
    rng = np.random.default_rng(0)
    a, b = rng.random((REFERENCE_POINTS, 2)), rng.random((REFERENCE_POINTS, 2))
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        total = 0.0
        for i in range(REFERENCE_ITERATIONS):
            d = a[:, None, :] - b[None, :, :]
            k = np.exp(-(d * d).sum(axis=2) / (0.01 + 0.001 * i))
            col = k.sum(axis=0) + 1e-3
            total += float((k / col).sum())
        best = min(best, time.perf_counter() - t0)
        assert np.isfinite(total)
    return best


def _fmt(value: Any, digits: int = 4) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def _one_job(client: RegtreeClient, collection_id: int, model_id: int,
             args: argparse.Namespace) -> tuple[Any, Any, StageTimes, float, float]:
    """Submit the job and follow it to its end: (job, final state, stage times, submit
    time, done time)."""
    times = StageTimes()
    t_submit = time.monotonic()
    job = client.start_job(collection_id, model_id, method=args.method,
                           compare_direct=args.compare_direct)
    final = client.wait(job.id, poll=args.poll, timeout=args.timeout, on_progress=times.see,
                        raise_on_failure=False)
    return job, final, times, t_submit, time.monotonic()


def run(
    args: argparse.Namespace, url: str, shapes: list[tuple[str, np.ndarray]], label: str
) -> int:
    rows: list[tuple[str, float, str]] = []
    n_points = [len(p) for _, p in shapes]
    with (
        tempfile.TemporaryDirectory(prefix="regtree-bench-files-") as tmp,
        RegtreeClient(url, api_key=args.api_key, timeout=600) as client,
    ):
        files = write_point_files(shapes, Path(tmp))
        size = sum(f.stat().st_size for f in files)

        t0 = time.monotonic()
        collection = client.create_collection(f"bench {label}", f"bench_service.py, {label}")
        stored = client.upload_files(collection.id, files, batch_size=100)
        rows.append(("upload", time.monotonic() - t0, f"{len(stored)} shapes, {size / 1e6:.1f} MB"))

        # after the upload (the workers may still be starting: the table shows the lesser)
        reference = [machine_reference()]
        by_name = {s.name: s.id for s in stored}
        model_name = args.model or shapes[0][0]
        if model_name not in by_name:
            print(f"no shape named {model_name!r}; names look like {shapes[0][0]!r}")
            return 2
        job, final, times, t_submit, t_done = _one_job(client, collection.id,
                                                       by_name[model_name], args)
        if final.started_at and final.created_at:
            queued = (final.started_at - final.created_at).total_seconds()
            rows.append(("queued wait", queued, "server created_at -> started_at"))
        for stage, seconds, items in times.rows():
            rows.append((stage, seconds, f"{items} items"))
        if final.status != "succeeded":
            print(f"job {job.id} ended {final.status}: {final.error}")
            _table(rows)
            return 1

        t1 = time.monotonic()
        result = client.result(job.id)
        rows.append(("result fetch", time.monotonic() - t1, f"{len(result.subjects)} subjects"))
        t1 = time.monotonic()
        full = client.result_document(job.id, full=True)
        rows.append(
            ("result fetch full", time.monotonic() - t1, f"{len(str(full)) / 1e6:.1f} MB as JSON")
        )
        rows.append(("job (submit -> done)", t_done - t_submit, f"{job.method}, poll {args.poll}s"))
        # the same job again in the same workers (no process starts any more): the machine's
        # own swings between runs are often larger than a change being measured
        repeats = [t_done - t_submit]
        for _ in range(args.repeat - 1):
            again, ended, stages, t0, t1 = _one_job(client, collection.id, by_name[model_name],
                                                   args)
            if ended.status != "succeeded":
                print(f"job {again.id} ended {ended.status}: {ended.error}")
                return 1
            repeats.append(t1 - t0)
            parts = ", ".join(f"{name} {sec:.2f}" for name, sec, _ in stages.rows())
            rows.append((f"job again ({len(repeats)})", t1 - t0, parts))
        if len(repeats) > 1:
            rows.append(("job, median of runs", float(np.median(repeats)),
                         f"{len(repeats)} runs: " + ", ".join(f"{t:.2f}" for t in repeats)))
        reference.append(machine_reference())
        rows.append(("machine reference", min(reference),
                     f"numpy: {REFERENCE_ITERATIONS} kernel passes over {REFERENCE_POINTS} x "
                     f"{REFERENCE_POINTS} pairs, in this process: before the jobs "
                     + ", after ".join(f"{t:.3f}" for t in reference)))

    print(
        f"\nregtree service bench: {label}: {len(shapes)} shapes, points per shape "
        f"min {min(n_points)} / median {int(np.median(n_points))} / max {max(n_points)}, "
        f"model {model_name!r}, {args.workers} embedded workers"
        + (f", compiled passes {compiled_simd() or 'none (numpy)'}" if args.url is None
           else f" (service at {args.url})")
    )
    _table(rows)
    summary = result.summary
    tree = summary.get("layer_ge_3") or {}
    direct = (summary.get("direct") or {}).get("layer_ge_3") or {}
    print(
        f"\nattached {summary.get('attached')}/{summary.get('subjects')}, "
        f"depth {summary.get('depth')}, layer >= 3: {tree.get('count', 0)} subjects"
    )
    print(f"{'e at layer >= 3':24s} {'mean':>10s} {'p95':>10s}")
    print(f"{'dynamic tree':24s} {_fmt(tree.get('mean')):>10s} {_fmt(tree.get('p95')):>10s}")
    print(f"{'direct CPD':24s} {_fmt(direct.get('mean')):>10s} {_fmt(direct.get('p95')):>10s}")
    thresholds = result.thresholds
    if thresholds:
        print("thresholds: " + ", ".join(f"{k} {_fmt(v)}" for k, v in thresholds.items()))
    return 0


def _table(rows: list[tuple[str, float, str]]) -> None:
    print(f"\n{'stage':24s} {'seconds':>9s}  notes")
    print(f"{'-' * 24} {'-' * 9}  {'-' * 30}")
    for name, seconds, note in rows:
        print(f"{name:24s} {seconds:9.2f}  {note}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--url", help="use a running service instead of starting one")
    parser.add_argument("--api-key", default=os.environ.get("REGTREE_API_KEY") or None)
    parser.add_argument("--workers", type=int, default=2, help="embedded workers (default 2)")
    parser.add_argument(
        "--points",
        type=int,
        default=None,
        help="resample each shape to at most N points before uploading",
    )
    parser.add_argument("--model", help="name of the model shape (default: the first file)")
    parser.add_argument(
        "--method", default="dynamic_tree", choices=["dynamic_tree", "static_tree", "direct"]
    )
    parser.add_argument(
        "--allow-generated",
        action="store_true",
        help="run on a generated chained family when the glyph set is missing",
    )
    parser.add_argument(
        "--compare-direct",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also run direct CPD from the model, as issue 9's first target (default on)",
    )
    parser.add_argument("--poll", type=float, default=0.2, help="seconds between polls")
    parser.add_argument("--repeat", type=int, default=1,
                        help="run the job this many times in the same workers and print "
                        "every run's time and their median (default 1)")
    parser.add_argument(
        "--timeout",
        type=float,
        default=3 * 3600,
        help="give up waiting for the job after this many seconds",
    )
    args = parser.parse_args(argv)
    if args.points is not None and args.points < 3:
        parser.error("--points must be at least 3")
    if args.repeat < 1:
        parser.error("--repeat must be at least 1")

    if sorted(EDGES.glob("*_edge.txt")):
        shapes, label = load_edges(args.points), "glyphs_yong edges"
    elif args.allow_generated:
        print(f"{EDGES} is missing: running on a generated chained family (--allow-generated)")
        shapes, label = generated(args.points), "generated chained family"
    else:
        print(
            f"{EDGES} is missing (the shared data folder sits beside the project, "
            "../shared/data); nothing to benchmark. Pass --allow-generated to run on a "
            "generated family instead."
        )
        return 0
    if args.points is not None:
        label += f", resampled to <= {args.points} points"

    if args.url is not None:
        return run(args, args.url, shapes, label)
    with tempfile.TemporaryDirectory(prefix="regtree-bench-") as workdir:
        with local_service(args.workers, Path(workdir)) as url:
            return run(args, url, shapes, label)


if __name__ == "__main__":
    raise SystemExit(main())
