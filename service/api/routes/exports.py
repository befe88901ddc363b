"""A job's result for integrators: the similarity D, per-subject CSV, and one ZIP of it all.

* ``GET /v1/jobs/{id}/similarity``: the D the job computed and each shape's nearest shapes;
* ``GET /v1/jobs/{id}/result.csv``: one row per subject (the filters of ``/result``);
* ``GET /v1/jobs/{id}/export.zip``: result.json (full), result.csv, similarity.json, the
  tree (SVG, PNG), the summary picture and, if asked, every subject's overlay.
"""

from __future__ import annotations

import csv
import io
import json
import re
import zipfile
from collections.abc import Mapping, Sequence
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Query, Response
from sqlalchemy.orm import Session, undefer

from service.api.deps import DbDep
from service.api.problems import ProblemError, operation
from service.api.routes.results import (
    LeafQuery,
    MinConfidenceQuery,
    SortQuery,
    result_document,
    root_subject,
    stored_result,
)
from service.contract.names import ProblemType, made_from_image, subject_status
from service.contract.result import SimilarityDocument
from service.jobs.document import json_safe
from service.models import Job, Result, Shape
from service.schemas import DbId

router = APIRouter(prefix="/jobs", tags=["exports"])

#: The columns of ``result.csv``, in order.
CSV_COLUMNS = (
    "shape_id",
    "name",
    "position",
    "status",
    "attached",
    "leaf",
    "layer",
    "parent_shape_id",
    "parent_name",
    "path_shape_ids",
    "similarity",
    "error",
    "direct_error",
    "confidence",
    "disagreement",
    "reason",
)


def similarity_document(
    session: Session, job_id: int, *, k: int = 5, matrix: bool = True
) -> dict[str, Any]:
    """The similarity D of a succeeded job, and each shape's ``k`` nearest shapes."""
    stored_result(session, job_id)
    result = session.get(Result, job_id, options=[undefer(Result.similarity_npy)])
    assert result is not None
    D = result.similarity
    document = result.document
    shape_ids = [int(i) for i in document.get("shape_ids") or []]
    if D is None or D.shape != (len(shape_ids), len(shape_ids)):
        raise ProblemError(
            409,
            f"job {job_id} kept no similarity matrix (its result was stored before the "
            "similarity was kept); run the job again to get it",
            type_=ProblemType.NO_SIMILARITY,
        )
    names = [str(n) for n in document.get("names") or []]
    names += [""] * (len(shape_ids) - len(names))
    off = ~np.eye(len(shape_ids), dtype=bool)
    nearest = []
    for j, sid in enumerate(shape_ids):
        onto = D[:, j]
        candidates = [i for i in np.argsort(onto, kind="stable") if off[i, j]]
        chosen = [i for i in candidates if np.isfinite(onto[i])][:k]
        nearest.append(
            {
                "shape_id": sid,
                "name": names[j],
                "nearest": [
                    {"shape_id": shape_ids[i], "name": names[i], "D": float(onto[i])}
                    for i in chosen
                ],
            }
        )
    out: dict[str, Any] = {
        "job_id": job_id,
        "shape_ids": shape_ids,
        "names": names,
        "computed_pairs": int(np.isfinite(D[off]).sum()),
        "nearest": nearest,
    }
    if matrix:
        out["D"] = json_safe(D)
    return out


@operation(
    router.get, "/{job_id}/similarity",
    "The similarity D the job computed, and each shape's nearest shapes", (404, 409, 422),
    response_model=SimilarityDocument, response_model_exclude_unset=True,
    description="D (eq. 9, affine ICP with bidirectional distance) between the job's shapes, "
    "in the order of `shape_ids`: `D[i][j]` moves shape i onto shape j (the direction the "
    "tree uses, member onto subject), null for pairs the job did not need. `nearest` lists, "
    "for every shape, the k shapes with the smallest D onto it. 409 "
    "(`/problems/no-similarity`) for a result stored before the similarity was kept.",
)
def get_similarity(
    job_id: DbId,
    db: DbDep,
    k: Annotated[int, Query(ge=1, le=100, description="Nearest shapes per shape.")] = 5,
    matrix: Annotated[bool, Query(description="Include the matrix D itself.")] = True,
) -> dict[str, Any]:
    with db.read() as session:
        return similarity_document(session, job_id, k=k, matrix=matrix)


def _csv_number(value: Any) -> str:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return ""
    return repr(value) if np.isfinite(value) else ""


def subjects_csv(document: Mapping[str, Any], subjects: Sequence[Mapping[str, Any]]) -> str:
    """One row per subject (:data:`CSV_COLUMNS`); empty cells for missing values."""
    names = dict(zip(document.get("shape_ids") or [], document.get("names") or [], strict=False))
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\r\n")
    writer.writerow(CSV_COLUMNS)
    for s in subjects:
        parent = s.get("parent_shape_id")
        path = s.get("path_shape_ids") or []
        writer.writerow(
            [
                s.get("shape_id"),
                s.get("name", ""),
                s.get("position", s.get("index", "")),
                s.get("status") or subject_status(s),
                "true" if s.get("attached") else "false",
                "true" if s.get("leaf") else "false",
                "" if s.get("layer") is None else s["layer"],
                "" if parent is None else parent,
                "" if parent is None else names.get(parent, ""),
                " ".join(str(p) for p in path if p is not None),
                _csv_number(s.get("similarity")),
                _csv_number(s.get("error")),
                _csv_number(s.get("direct_error")),
                _csv_number(s.get("confidence")),
                _csv_number(s.get("disagreement")),
                s.get("reason", ""),
            ]
        )
    return buffer.getvalue()


@operation(
    router.get, "/{job_id}/result.csv", "A job's per-subject results as CSV", (404, 409, 422),
    response_class=Response,
    responses={200: {"content": {"text/csv": {}}, "description": "One row per subject."}},
    description="One row per subject, with the columns " + ", ".join(CSV_COLUMNS) + ". "
    "Numbers at full precision, empty where there is none (an unattached subject has no "
    "layer, parent or e); path_shape_ids is space-separated, root first. min_confidence, "
    "leaf and sort choose and order the rows as for the JSON result.",
)
def get_result_csv(
    job_id: DbId,
    db: DbDep,
    min_confidence: MinConfidenceQuery = None,
    leaf: LeafQuery = None,
    sort: SortQuery = "position",
) -> Response:
    with db.read() as session:
        document = result_document(
            session, job_id, sort=sort, min_confidence=min_confidence, leaf=leaf
        )
    return Response(
        content=subjects_csv(document, document["subjects"]),
        media_type="text/csv; charset=utf-8",
        headers={"Content-Disposition": f'attachment; filename="job-{job_id}-result.csv"'},
    )


def _stem(name: str) -> str:
    return (re.sub(r"[^\w.+-]+", "_", name).strip("._") or "shape")[:80]


def _pictures(
    session: Session, job: Job, document: Mapping[str, Any], subject_pictures: bool
) -> dict[str, bytes]:
    from service.plots import render_subject, render_summary, render_tree

    files = {
        "tree.svg": render_tree(document, fmt="svg").data,
        "tree.png": render_tree(document, fmt="png").data,
        "summary.png": render_summary(document, fmt="png").data,
    }
    if subject_pictures:
        for subject in document.get("subjects") or []:
            shape = session.get(Shape, int(subject["shape_id"]))
            if shape is None:
                continue  # deleted since the job ran: its points are gone
            picture = render_subject(
                subject,
                shape.points,
                fmt="png",
                method=job.method,
                y_down=made_from_image(shape.source_format),
            )
            files[f"subjects/{shape.id}-{_stem(shape.name)}.png"] = picture.data
    return files


SubjectPicturesQuery = Annotated[
    bool, Query(description="Also draw every subject's overlay (one PNG per subject).")
]


@operation(
    router.get, "/{job_id}/export.zip",
    "A whole job as one ZIP: JSON, CSV and pictures", (404, 409, 422),
    response_class=Response,
    responses={
        200: {"content": {"application/zip": {}}, "description": "The job as one ZIP file."}
    },
    description="`result.json` (the full result: every subject with its warped model, "
    "correspondences and transform, and `root_subject`: the model's own entry with the "
    "identity transform), `result.csv`, `similarity.json` (when the job kept it), `job.json`, "
    "`tree.svg`, `tree.png`, `summary.png` and, with `subject_pictures=true`, "
    "`subjects/<shape_id>-<name>.png` (the model warped onto each subject; slower).",
)
def get_export_zip(
    job_id: DbId, db: DbDep, subject_pictures: SubjectPicturesQuery = False
) -> Response:
    from service.api.routes.jobs import job_out

    with db.read() as session:
        document = result_document(session, job_id, full=True)
        job = session.get(Job, job_id)
        assert job is not None
        document["root_subject"] = root_subject(session, job_id, document)
        try:
            similarity: dict[str, Any] | None = similarity_document(session, job_id)
        except ProblemError:
            similarity = None
        job_json = job_out(session, job).model_dump(mode="json")
        pictures = _pictures(session, job, document, subject_pictures)
    files: dict[str, bytes] = {
        "result.json": json.dumps(document, ensure_ascii=False).encode("utf-8"),
        "result.csv": subjects_csv(document, document["subjects"]).encode("utf-8"),
        "job.json": json.dumps(job_json, ensure_ascii=False, indent=1).encode("utf-8"),
    }
    if similarity is not None:
        files["similarity.json"] = json.dumps(similarity).encode("utf-8")
    files.update(pictures)
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, data in files.items():
            archive.writestr(f"job-{job_id}/{name}", data)
    return Response(
        content=buffer.getvalue(),
        media_type="application/zip",
        headers={"Content-Disposition": f'attachment; filename="job-{job_id}.zip"'},
    )
