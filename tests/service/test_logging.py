"""service/core/logging.py and the log settings: readable lines on a terminal, JSON lines
otherwise or when asked."""

from __future__ import annotations

import io
import json
import logging
from collections.abc import Callable, Iterator

import pytest

from service.core.config import Settings
from service.core.logging import configure_logging, resolve_format
from service.embedded import announce, public_url
from tests.service.conftest import Service


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.fixture(autouse=True)
def _restore_logging() -> Iterator[None]:
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


def _log(stream: io.StringIO, fmt: str) -> str:
    configure_logging("INFO", fmt, stream=stream)
    logging.getLogger("regtree.test").info("job done", extra={"job_id": 7, "worker": "a b"})
    logging.getLogger("regtree.test").debug("not shown")
    return stream.getvalue()


def test_auto_is_text_on_a_terminal_and_json_otherwise() -> None:
    text = _log(Terminal(), "auto")
    assert text.count("\n") == 1
    assert " INFO    regtree.test: job done  job_id=7 worker=\"a b\"" in text
    assert not text.startswith("{")
    line = _log(io.StringIO(), "auto")
    doc = json.loads(line)
    assert (doc["level"], doc["logger"], doc["msg"], doc["job_id"]) == (
        "info", "regtree.test", "job done", 7
    )


def test_a_format_asked_for_wins_over_the_terminal() -> None:
    assert json.loads(_log(Terminal(), "json"))["worker"] == "a b"
    assert "regtree.test: job done" in _log(io.StringIO(), "text")
    with pytest.raises(ValueError, match="auto, json or text"):
        resolve_format("yaml", io.StringIO())


def test_settings_choose_the_format(monkeypatch: pytest.MonkeyPatch) -> None:
    assert Settings(_env_file=None).log_style == "auto"  # type: ignore[call-arg]
    monkeypatch.setenv("REGTREE_LOG_FORMAT", "json")
    assert Settings(_env_file=None).log_style == "json"  # type: ignore[call-arg]
    monkeypatch.setenv("REGTREE_LOG_JSON", "false")  # the older switch, when set, wins
    assert Settings(_env_file=None).log_style == "text"  # type: ignore[call-arg]
    monkeypatch.setenv("REGTREE_LOG_FORMAT", "xml")
    with pytest.raises(ValueError, match="log_format"):
        Settings(_env_file=None)  # type: ignore[call-arg]


def test_serve_announces_the_results_page() -> None:
    out = io.StringIO()
    settings = Settings(_env_file=None, database_url="sqlite:///x.sqlite")  # type: ignore[call-arg]
    announce(settings, "0.0.0.0", 8123, out)
    text = out.getvalue()
    assert "results page  http://127.0.0.1:8123/ui\n" in text
    assert "API docs      http://127.0.0.1:8123/docs\n" in text
    assert "sqlite:///x.sqlite" in text
    assert public_url("::1", 80) == "http://[::1]:80"
    assert public_url("example.internal", 8000) == "http://example.internal:8000"


def test_serve_prints_the_ui_address_and_logs_json_when_not_a_terminal(
    make_service: Callable[..., Service],
) -> None:
    svc = make_service(workers=0, env={"REGTREE_LOG_LEVEL": "INFO"}).start()
    with svc.client() as client:
        assert client.get("/healthz").status_code == 200
    svc.stop()
    lines = svc.logs().splitlines()
    assert f"  results page  {svc.base_url}/ui" in lines
    logs = [json.loads(line) for line in lines if line.startswith("{")]
    assert any(doc["msg"] == "request" or doc["logger"] == "regtree.access" for doc in logs)
    # every line is the announcement or a JSON log line: no uvicorn text lines
    assert all(line.startswith(("{", "regtree is serving", "  ", "Stop it")) for line in lines)
