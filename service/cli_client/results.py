"""``regtree results``, ``export`` and ``similarity``."""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from service.contract.names import (
    is_attached,
    made_from_image,
    subject_status,
)

if TYPE_CHECKING:
    from service.client import JobStatus, RegtreeClient, SubjectQuery

from service.cli_client._common import (
    CLIError,
    Exit,
    _cell,
    _fail,
    _num,
    _out,
)

# --- results -----------------------------------------------------------------------------


def _file_stem(name: str) -> str:
    stem = re.sub(r"[^\w.+-]+", "_", name).strip("._") or "shape"
    return stem[:120]


def select_subjects(subjects: Sequence[Mapping[str, Any]], which: str | int) -> list[Any]:
    if which == "all":
        return list(subjects)
    if which == "attached":
        return [s for s in subjects if is_attached(s)]
    return list(subjects[: int(which)])


def subjects_table(doc: Mapping[str, Any], subjects: Sequence[Mapping[str, Any]]) -> list[str]:
    """One line per subject, in the given order: shape id, name, layer, parent, e, direct e
    (not for a direct job, whose e is direct CPD's), confidence, disagreement (how far apart
    two registrations that err differently put the model's points, in the shape's RMS
    radius; "-" where no symmetric finish ran) and status ("tree", "leaf" for a
    low-confidence leaf, "unattached")."""
    compares = doc.get("method") != "direct"
    names = dict(zip(doc.get("shape_ids") or [], doc.get("names") or [], strict=False))
    for s in doc.get("subjects") or []:
        if isinstance(s, Mapping) and "shape_id" in s and s.get("name") is not None:
            names[s["shape_id"]] = s["name"]
    width = min(32, max([4, *(len(str(s.get("name", ""))) for s in subjects)]))
    direct_e = f" {'direct e':>11}" if compares else ""
    lines = [
        f"{'shape':>8}  {_cell('name', width)}  {'layer':>5}  {_cell('parent', 16)}"
        f" {'e':>11}{direct_e} {'confidence':>10} {'disagreement':>12}  status"
    ]
    for s in subjects:
        layer = s.get("layer")
        parent = s.get("parent_shape_id")
        confidence = s.get("confidence")
        spread = s.get("disagreement")
        lines.append(
            f"{s.get('shape_id', '?'):>8}  {_cell(str(s.get('name', '')), width)}"
            f"  {('-' if layer is None else layer):>5}"
            f"  {_cell('-' if parent is None else str(names.get(parent, parent)), 16)}"
            f" {_num(s.get('error'))}"
            + (f" {_num(s.get('direct_error'))}" if compares else "")
            + (
                f" {confidence:10.3f}"
                if isinstance(confidence, int | float) and not isinstance(confidence, bool)
                else f" {'-':>10}"
            )
            + (
                f" {spread:12.4f}"
                if isinstance(spread, int | float) and not isinstance(spread, bool)
                else f" {'-':>12}"
            )
            + f"  {subject_status(s)}"
        )
    return lines


def _subject_query(args: argparse.Namespace) -> SubjectQuery:
    """The options of ``regtree results`` that the service's result query takes."""
    query: SubjectQuery = {}
    if args.sort is not None:
        query["sort"] = args.sort
    if args.min_confidence is not None:
        query["min_confidence"] = args.min_confidence
    if args.leaf is not None:
        query["leaf"] = args.leaf
    return query


def _query_text(query: Mapping[str, Any]) -> str:
    parts = []
    if "min_confidence" in query:
        parts.append(f"confidence >= {query['min_confidence']:g}")
    if query.get("leaf") is True:
        parts.append("low-confidence leaves only")
    elif query.get("leaf") is False:
        parts.append("no low-confidence leaves")
    if query.get("sort") not in (None, "position"):
        key = str(query["sort"])
        direction = "descending" if key.startswith("-") else "ascending"
        parts.append(f"by {key.removeprefix('-')}, {direction}")
    return "; ".join(parts)


#: The short name of each method's own e columns in :func:`summary_table`.
_METHOD_COLUMNS = {"dynamic_tree": "tree", "static_tree": "static", "direct": "direct"}


def summary_table(doc: Mapping[str, Any]) -> list[str]:
    """Per-layer counts with mean / p95 of e, then layer >= 3 and all attached, for the
    job's method (columns named after it: tree, static, direct) and, beside a tree, for
    direct CPD (``-`` where the job did not compare with it)."""
    from service.plots import layer_statistics

    subjects = [s for s in doc.get("subjects") or [] if isinstance(s, Mapping)]
    summary = doc.get("summary") or {}
    direct = summary.get("direct") or {}
    method = str(doc.get("method"))
    own = _METHOD_COLUMNS.get(method, "e")
    compares = method != "direct"  # a direct job is direct CPD: nothing to compare with
    names = dict(zip(doc.get("shape_ids") or [], doc.get("names") or [], strict=False))
    root = doc.get("root_shape_id")
    counts: dict[int, int] = {}
    unattached = 0
    for s in subjects:
        if is_attached(s) and s.get("layer") is not None:
            counts[int(s["layer"])] = counts.get(int(s["layer"]), 0) + 1
        else:
            unattached += 1
    tree_stats, direct_stats = layer_statistics(doc)
    leaves = sum(1 for s in subjects if s.get("leaf"))
    as_leaves = f" ({leaves} as low-confidence leaves)" if leaves else ""
    lines = [
        f"job {doc.get('job_id')}: {doc.get('method')}, model {names.get(root, root)!r} "
        f"(shape {root}); {len(subjects)} subjects, {sum(counts.values())} attached"
        f"{as_leaves}, {unattached} unattached, depth "
        f"{summary.get('depth', max(counts, default=1))}"
    ]
    thresholds = doc.get("thresholds") or {}
    for key in ("similarity", "error"):
        if isinstance(thresholds.get(key), int | float):
            lines.append(
                f"{key} threshold {thresholds[key]:.4g}  {thresholds.get(key + '_rule', '')}"
            )
    columns = f"{own + ' mean':>11} {own + ' p95':>11}"
    if compares:
        columns += f" {'direct mean':>11} {'direct p95':>11}"

    def cells(t: Mapping[str, Any], d: Mapping[str, Any]) -> str:
        out = f"{_num(t.get('mean'))} {_num(t.get('p95'))}"
        return out + (f" {_num(d.get('mean'))} {_num(d.get('p95'))}" if compares else "")

    header = f"{'layer':>12} {'subjects':>8} {columns}"
    lines += ["", "e (eq. 10) per layer", header, f"{1:>12} {1:>8}  (the model)"]
    for layer in sorted(counts):
        t, d = tree_stats.get(layer) or {}, direct_stats.get(layer) or {}
        lines.append(f"{layer:>12} {counts[layer]:>8} {cells(t, d)}")
    if unattached:
        lines.append(f"{'unattached':>12} {unattached:>8}")
    lines += ["", f"{'':>12} {'count':>8} {columns}"]
    for label, key in (("layer >= 3", "layer_ge_3"), ("all attached", "all")):
        t, d = summary.get(key) or {}, direct.get(key) or {}
        lines.append(f"{label:>12} {t.get('count', 0):>8} {cells(t, d)}")
    if compares and not direct:
        lines.append("(direct CPD was not compared: the job ran with --no-compare-direct)")
    return lines


def cmd_results(args: argparse.Namespace, rt: RegtreeClient) -> int:
    job = rt.get_job(args.job)
    out: Path | None = args.out
    # every subject, for the summary, result.json and the tree; the full one to draw from
    query = _subject_query(args)
    if args.csv:
        sys.stdout.write(rt.result_csv(args.job, **query))
        sys.stdout.flush()
        return Exit.OK
    doc = rt.result_document(args.job, full=out is not None)
    # the subject lines (and pictures): chosen and ordered by the service
    listed = rt.result_document(args.job, **query)["subjects"] if query else doc["subjects"]
    if out is None:
        for line in summary_table(doc):
            _out(line)
        _print_subjects(doc, listed, query)
        return Exit.OK
    return _write_results(args, rt, job, doc, listed, query, out)


def _print_subjects(
    doc: Mapping[str, Any], listed: Sequence[Mapping[str, Any]], query: Mapping[str, Any]
) -> None:
    total = len(doc.get("subjects") or [])
    chosen = _query_text(query)
    _out("")
    _out(f"subjects ({chosen}): {len(listed)} of {total}" if chosen else f"subjects: {total}")
    for line in subjects_table(doc, listed):
        _out(line)
    if any(s.get("leaf") for s in listed):
        _out(
            "leaf: a low-confidence leaf, which the tree could not accept; it got its best "
            "registration anyway and is never a parent (its reason is in result.json)"
        )


def _write_results(
    args: argparse.Namespace,
    rt: RegtreeClient,
    job: JobStatus,
    doc: dict[str, Any],
    listed: Sequence[Mapping[str, Any]],
    query: Mapping[str, Any],
    out: Path,
) -> int:
    from service.plots import render_subject, render_summary, render_tree

    written: list[Path] = []
    problems: list[str] = []

    def write(path: Path, data: bytes) -> None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
        except OSError as e:
            raise CLIError(f"cannot write {path}: {e.strerror or e}", Exit.FAILED) from e
        written.append(path)

    write(out / "result.json", json.dumps(doc, indent=1, ensure_ascii=False).encode("utf-8"))
    write(out / "result.csv", rt.result_csv(args.job).encode("utf-8"))
    for name, draw in (
        ("tree.svg", lambda: render_tree(doc, fmt="svg")),
        ("tree.png", lambda: render_tree(doc, fmt="png")),
        ("summary.png", lambda: render_summary(doc, fmt="png")),
    ):
        try:
            write(out / name, draw().data)
        except (ValueError, KeyError, TypeError) as e:
            problems.append(f"{name}: {e}")

    full = {s.get("shape_id"): s for s in doc.get("subjects") or [] if isinstance(s, Mapping)}
    ordered = [full.get(s.get("shape_id"), s) for s in listed]
    chosen = select_subjects(ordered, args.subjects)
    used: set[str] = set()
    tty = sys.stdout.isatty()
    for number, subject in enumerate(chosen, start=1):
        shape_id = int(subject["shape_id"])
        name = str(subject.get("name", shape_id))
        stem = _file_stem(name)
        if stem in used:
            stem = f"{stem}-{shape_id}"
        used.add(stem)
        path = out / "subjects" / f"{stem}.{args.format}"
        try:
            shape = rt.get_shape(job.collection_id, shape_id)
            if shape.points is None:
                raise ValueError("the service sent no points")
            # as the service draws it: pixel coordinates of an image downwards
            y_down = made_from_image(shape.source_format) if args.y_down is None else args.y_down
            picture = render_subject(
                subject, shape.points, fmt=args.format, method=job.method, y_down=y_down
            )
        except (ValueError, KeyError, TypeError) as e:
            problems.append(f"subject {name!r} (shape {shape_id}): {e}")
            continue
        write(path, picture.data)
        if tty:
            sys.stdout.write(f"\r\x1b[Ksubject pictures {number}/{len(chosen)}")
            sys.stdout.flush()
    if tty and chosen:
        sys.stdout.write("\r\x1b[K")

    for line in summary_table(doc):
        _out(line)
    _print_subjects(doc, listed, query)
    _out("")
    subject_files = [p for p in written if p.parent.name == "subjects"]
    for path in written:
        if path.parent.name != "subjects":
            _out(f"wrote {path}")
    if subject_files:
        _out(f"wrote {len(subject_files)} subject picture(s) in {out / 'subjects'}")
    if problems:
        for problem in problems:
            print(f"regtree: warning: not drawn: {problem}", file=sys.stderr)
        return _fail(f"{len(problems)} picture(s) could not be drawn", Exit.FAILED)
    return Exit.OK


def cmd_export(args: argparse.Namespace, rt: RegtreeClient) -> int:
    out: Path = args.out or Path(f"job-{args.job}.zip")
    data = rt.export_zip(args.job, subject_pictures=args.subject_pictures)
    try:
        out.write_bytes(data)
    except OSError as e:
        raise CLIError(f"cannot write {out}: {e.strerror or e}", Exit.FAILED) from e
    _out(f"wrote {out} ({len(data)} bytes)")
    return Exit.OK


def cmd_similarity(args: argparse.Namespace, rt: RegtreeClient) -> int:
    sim = rt.similarity(args.job, k=args.k, matrix=False)
    names = dict(zip(sim.shape_ids, sim.names, strict=True))
    n = len(sim.shape_ids)
    _out(f"job {args.job}: D computed for {sim.computed_pairs} of {n * (n - 1)} ordered pairs")
    width = min(32, max([4, *(len(name) for name in sim.names)]))
    _out(f"{'shape':>8}  {_cell('name', width)}  nearest (D onto it)")
    for sid in sim.shape_ids:
        near = ", ".join(f"{names.get(o, o)} {d:.4g}" for o, d in sim.nearest.get(sid, []))
        _out(f"{sid:>8}  {_cell(names[sid], width)}  {near or '-'}")
    return Exit.OK
