"""``regtree demo``: register the bundled demo collection through the real service.

It starts the same API server and worker processes as ``regtree serve`` (on a free local
port, with the configured database, ``./var/regtree.sqlite`` by default), uploads the demo
shapes over HTTP (run again on the same database, it reuses its collection ``demo: NAME``
and the shapes of the demo's names there, uploading only those missing), submits a
dynamic-tree job with the first shape as model, polls it while printing progress, and prints
a summary of the result.
"""

from __future__ import annotations

import sys
import time
from importlib import resources
from io import BytesIO
from typing import Any, TextIO

import httpx
import numpy as np

from service.client import JobStatus
from service.core.config import Settings
from service.embedded import BackgroundStack
from service.progress import Progress, outcome_line


def load_demo_shapes() -> tuple[str, dict[str, np.ndarray]]:
    """The first ``service/demo/*.npz`` (keys: shape names), else a generated family."""
    folder = resources.files("service") / "demo"
    if folder.is_dir():
        for entry in sorted(folder.iterdir(), key=lambda e: e.name):
            if entry.name.endswith(".npz"):
                with np.load(BytesIO(entry.read_bytes()), allow_pickle=False) as npz:
                    return entry.name.removesuffix(".npz"), {k: npz[k] for k in npz.files}
    from registration.synthetic import chained_family

    family = chained_family(n_chains=3, chain_length=5, n_points=150, seed=0)
    return "chained_family (generated)", family.to_npz_dict()


def _fmt(stats: dict[str, Any] | None) -> str:
    if not stats or not stats.get("count"):
        return f"{'n/a':>12} {'n/a':>12} {0:>6}"
    return f"{stats['mean']:12.6f} {stats['p95']:12.6f} {stats['count']:>6}"


def summarise(result: dict[str, Any], out: Any = sys.stdout) -> None:
    """Print per-layer counts and mean / 95th percentile of e, tree against direct."""
    subjects = result["subjects"]
    layers: dict[str, int] = {}
    for s in subjects:
        key = str(s.get("layer")) if s.get("attached", s.get("layer") is not None) else "-"
        layers[key] = layers.get(key, 0) + 1
    print(f"\nroot (model) shape: {result.get('root_shape_id')}", file=out)
    thresholds = result.get("thresholds") or {}
    for key in ("similarity", "error"):
        if key in thresholds:
            rule = thresholds.get(f"{key}_rule", "")
            print(f"{key} threshold: {thresholds[key]:.6g}  {rule}", file=out)
    print("\nlayer   subjects", file=out)
    for key in sorted(layers, key=lambda v: (not v.isdigit(), int(v) if v.isdigit() else 0)):
        label = "unattached" if key == "-" else key
        print(f"{label:>10} {layers[key]:6}", file=out)
    summary = result.get("summary") or {}
    direct = summary.get("direct") or {}
    print("\nerror e (eq. 10)                   mean          p95  count", file=out)
    print(f"tree,   all attached      {_fmt(summary.get('all'))}", file=out)
    print(f"direct, all               {_fmt(direct.get('all'))}", file=out)
    print(f"tree,   layer >= 3        {_fmt(summary.get('layer_ge_3'))}", file=out)
    print(f"direct, layer >= 3        {_fmt(direct.get('layer_ge_3'))}", file=out)
    if "attached" in summary:
        print(
            f"\nattached {summary['attached']} of {summary.get('subjects')} subjects"
            f" ({summary.get('leaves', 0)} as low-confidence leaves); "
            f"unattached {summary.get('unattached')}; depth {summary.get('depth')}",
            file=out,
        )


def follow_job(
    client: httpx.Client, location: str, out: TextIO, *, poll: float = 0.5
) -> dict[str, Any]:
    """Poll a job until it ends, drawing its progress as ``regtree watch`` does."""
    job_id = int(location.rstrip("/").rsplit("/", 1)[1])
    progress = Progress(job_id, out)
    try:
        while True:
            state: dict[str, Any] = client.get(location).raise_for_status().json()
            progress.update(JobStatus.from_json(state))
            if state["status"] in ("succeeded", "failed", "cancelled"):
                return state
            time.sleep(poll)
    finally:
        progress.end_line()


def _all(client: httpx.Client, path: str) -> list[dict[str, Any]]:
    """Every item of a paged list."""
    items: list[dict[str, Any]] = []
    while True:
        page = client.get(path, params={"offset": len(items)}).raise_for_status().json()
        items.extend(page["items"])
        if not page["items"] or len(items) >= page["total"]:
            return items


def _demo_collection(
    client: httpx.Client, title: str, shapes: dict[str, np.ndarray], out: TextIO
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The demo's collection and its shapes in demo order: reused when an earlier run left
    them (by name), so running the demo twice does not make two collections of one name."""
    found = [c for c in _all(client, "/v1/collections") if c["name"] == title]
    if found:
        collection = found[0]
        print(f"reusing collection {title!r} (id {collection['id']}) of an earlier demo run",
              file=out)
    else:
        collection = (
            client.post("/v1/collections", json={"name": title, "description": "regtree demo"})
            .raise_for_status()
            .json()
        )
    url = f"/v1/collections/{collection['id']}/shapes"
    held = {s["name"]: s for s in _all(client, url)}
    missing = [k for k in shapes if k not in held]
    if missing:
        batch = {"shapes": [{"name": k, "points": shapes[k].tolist()} for k in missing]}
        for s in client.post(url, json=batch).raise_for_status().json()["items"]:
            held[s["name"]] = s
    return collection, [held[k] for k in shapes]


def run_demo(
    settings: Settings,
    *,
    workers: int = 1,
    method: str = "dynamic_tree",
    out: TextIO | None = None,
) -> int:
    """Upload the demo shapes, run a job, show its progress and print the result on ``out``
    (stdout)."""
    out = out if out is not None else sys.stdout
    name, shapes = load_demo_shapes()
    print(
        f"demo collection {name!r}: {len(shapes)} shapes; database {settings.database_url}",
        file=out,
    )
    with BackgroundStack(settings, workers=max(1, workers)) as stack:
        headers = {}
        if settings.api_key is not None:
            headers["X-API-Key"] = settings.api_key.get_secret_value()
        with httpx.Client(base_url=stack.base_url, headers=headers, timeout=60) as client:
            collection, uploaded = _demo_collection(client, f"demo: {name}", shapes, out)
            job = client.post(
                "/v1/jobs",
                json={
                    "collection_id": collection["id"],
                    "model_shape_id": uploaded[0]["id"],
                    "method": method,
                    "compare_direct": True,
                },
            ).raise_for_status()
            location = job.headers["Location"]
            state = follow_job(client, location, out)
            if state["status"] != "succeeded":
                print(outcome_line(JobStatus.from_json(state)), file=out)
                print(f"job ended {state['status']}: {state['error']}", file=sys.stderr)
                return 1
            result = client.get(f"{location}/result").raise_for_status().json()
    # the line ``regtree watch`` ends with
    print(outcome_line(JobStatus.from_json(state), result.get("summary")), file=out)
    summarise(result, out)
    print(
        "\nsee it: `regtree serve`, then open /ui (the results page) and pick the collection "
        f"'demo: {name}'",
        file=out,
    )
    return 0
