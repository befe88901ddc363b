"""The JSON columns' codec (service.db.dumps_json / loads_json): orjson, with the standard
library for what orjson refuses, and the same values back as before."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import JSON, Column, Integer, MetaData, Table, insert, select

from service.db import create_db_engine, dumps_json, loads_json


def test_documents_come_back_as_the_standard_library_reads_them() -> None:
    doc = {
        "subjects": [{"index": 1, "error": 0.0051234567890123, "warped": [[1e-5, -2.5e300]],
                      "correspondence": [0, 7], "name": "永 ü", "parent": None,
                      "ok": True}],
        "options": {"working_points": 400, "nested": {"empty": [], "t": (1, 2)}},
    }
    text = dumps_json(doc)
    assert loads_json(text) == json.loads(json.dumps(doc))
    assert json.loads(text) == json.loads(json.dumps(doc))  # any JSON reader agrees


def test_what_only_the_codec_accepts_is_written_as_json_would_after_tolist() -> None:
    value = {1: np.arange(3), "x": np.float64(0.25), "y": np.int64(7), "z": np.float32(0.5)}
    assert loads_json(dumps_json(value)) == {"1": [0, 1, 2], "x": 0.25, "y": 7, "z": 0.5}
    # non-finite floats are not JSON: null (json.dumps wrote the invalid token NaN)
    assert loads_json(dumps_json({"e": math.nan, "f": [math.inf]})) == {"e": None, "f": [None]}


def test_what_orjson_refuses_falls_back_to_the_standard_library() -> None:
    huge = 2**70
    assert loads_json(dumps_json({"n": huge})) == {"n": huge}
    # text json.dumps wrote before (NaN is not JSON, but json.loads reads it)
    old = json.dumps({"e": math.nan})
    assert math.isnan(loads_json(old)["e"])
    with pytest.raises(json.JSONDecodeError):
        loads_json("{not json")


def test_engine_json_columns_use_the_codec(tmp_path: Path) -> None:
    engine = create_db_engine(f"sqlite:///{tmp_path / 'codec.db'}")
    table = Table("docs", MetaData(), Column("id", Integer, primary_key=True),
                  Column("document", JSON))
    table.metadata.create_all(engine)
    doc = {"warped": np.linspace(0.0, 1.0, 5).reshape(-1, 1), 3: "three", "e": math.nan}
    with engine.begin() as conn:
        conn.execute(insert(table).values(id=1, document=doc))
        raw = conn.exec_driver_sql("SELECT document FROM docs").scalar_one()
        back = conn.execute(select(table.c.document)).scalar_one()
    assert back == {"warped": [[0.0], [0.25], [0.5], [0.75], [1.0]], "3": "three", "e": None}
    assert json.loads(raw) == back  # stored as plain JSON text
    engine.dispose()
