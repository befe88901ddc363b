"""``regtree group``: group a collection's shapes by the mould that printed them (issue 11)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING, Any

from service.cli_client._common import Exit, _out, find_collection
from service.cli_client.watch import watch_job

if TYPE_CHECKING:
    from service.client import RegtreeClient


def cmd_group(args: argparse.Namespace, rt: RegtreeClient) -> int:
    collection = find_collection(rt, args.collection)
    job = rt.start_grouping(collection.id, threshold=args.threshold,
                            max_rotation=args.max_rotation)
    if not args.wait:
        _out(str(job.id))
        return Exit.OK
    if not args.json:
        _out(f"job {job.id}: grouping collection {collection.name!r} (id {collection.id}, "
             f"{job.n_shapes or collection.n_shapes} shapes)")
    code = watch_job(rt, job.id, poll=args.poll, cancel_on_interrupt=args.cancel_on_interrupt,
                     out=sys.stderr if args.json else None)
    if code != Exit.OK:
        return code
    doc = rt.groups(job.id)
    if args.gallery:
        rt.group_picture(job.id, "gallery", args.gallery)
    if args.dendrogram:
        rt.group_picture(job.id, "dendrogram", args.dendrogram)
    if args.json:
        _out(json.dumps(doc.model_dump(mode="json")))
        return Exit.OK
    _out(groups_table(doc.model_dump(mode="json")))
    return Exit.OK


def groups_table(doc: dict[str, Any]) -> str:
    """The groups as text: a header line, then one line per group and its members."""
    by_id = {i["shape_id"]: i for i in doc["instances"]}
    lines = [f"{doc['n_groups']} groups of {len(doc['shape_ids'])} shapes "
             f"(threshold {doc['threshold']:.4g}, {doc['threshold_source']})"]
    for g in doc["groups"]:
        rep = by_id[g["representative_shape_id"]]
        lines.append(f"group {g['label']}: {g['size']} shape(s), representative "
                     f"{rep['shape_id']} {rep['name']!r}, spread {g['spread']:.3f}")
        for sid in g["shape_ids"]:
            i = by_id[sid]
            lines.append(f"  {sid:>8}  {i['name'][:40]:<40}  confidence {i['confidence']:.2f}")
    return "\n".join(lines)
