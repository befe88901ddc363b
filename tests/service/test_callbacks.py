"""Job callbacks through real HTTP: a ``regtree serve`` subprocess calls a local receiver
(``http.server`` in a thread) that checks the signature, answers 500 once, and can hold a
request open; plus the signing and host rules on their own."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import httpx
import pytest

from service.client import RegtreeClient
from service.core.config import Settings
from service.jobs import callbacks
from tests.service.conftest import (
    REPO,
    Service,
    assert_problem,
    create_collection,
    family,
    submit_job,
    upload_family,
    wait_job,
)

SECRET = "s3cret-for-tests"


@dataclass
class Received:
    headers: dict[str, str]
    body: bytes


@dataclass
class Receiver:
    """A webhook receiver: answers each request with the next of ``statuses`` (then 200),
    and waits for ``release`` first while ``hold`` is set."""

    statuses: list[int] = field(default_factory=list)
    requests: list[Received] = field(default_factory=list)
    hold: threading.Event = field(default_factory=threading.Event)
    release: threading.Event = field(default_factory=threading.Event)
    arrived: threading.Event = field(default_factory=threading.Event)
    port: int = 0

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/hook"

    def verified(self) -> list[dict[str, Any]]:
        """The bodies of the requests whose signature is right, in order."""
        return [
            json.loads(r.body)
            for r in self.requests
            if callbacks.verify(
                SECRET,
                r.body,
                timestamp=r.headers.get("x-regtree-timestamp"),
                signature=r.headers.get("x-regtree-signature"),
            )
        ]


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    state = Receiver()

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:
            body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
            headers = {k.lower(): v for k, v in self.headers.items()}
            state.requests.append(Received(headers, body))
            state.arrived.set()
            if state.hold.is_set():
                state.release.wait(60)
            status = state.statuses.pop(0) if state.statuses else 200
            self.send_response(status)
            self.send_header("Content-Length", "0")
            self.end_headers()

        def log_message(self, *args: object) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    state.port = server.server_address[1]
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield state
    state.release.set()
    server.shutdown()
    server.server_close()


CALLBACK_ENV = {
    "REGTREE_CALLBACK_SECRET": SECRET,
    "REGTREE_CALLBACK_ALLOWED_HOSTS": "127.0.0.1",
    "REGTREE_CALLBACK_BACKOFF_SECONDS": "0.3",
    "REGTREE_CALLBACK_MAX_ATTEMPTS": "3",
    "REGTREE_PUBLIC_URL": "http://regtree.test",
}


def _collection(client: httpx.Client) -> tuple[int, list[int]]:
    cid = create_collection(client, "cb")
    return cid, upload_family(client, cid, family(1, 2, 30))


def _deliveries(
    client: httpx.Client, job_id: int, until: Callable[[dict[str, Any]], bool]
) -> dict[str, Any]:
    deadline = time.monotonic() + 60
    while True:
        body: dict[str, Any] = client.get(f"/v1/jobs/{job_id}/deliveries").json()
        if until(body):
            return body
        assert time.monotonic() < deadline, body
        time.sleep(0.1)


def test_callback_is_signed_and_retried_after_a_500(
    make_service: Callable[..., Service], receiver: Receiver
) -> None:
    receiver.statuses = [500]
    svc = make_service(env=CALLBACK_ENV).start()
    with svc.client() as client:
        cid, ids = _collection(client)
        job = submit_job(client, cid, ids[0], method="direct", callback_url=receiver.url)
        assert job["callback_url"] == receiver.url
        assert job["links"]["deliveries"] == f"/v1/jobs/{job['id']}/deliveries"
        assert wait_job(client, job["id"])["outcome"] == "succeeded"
        done = _deliveries(client, job["id"], lambda d: d["state"] == "delivered")

    assert [a["status_code"] for a in done["items"]] == [500, 200]
    assert [a["error"] for a in done["items"]] == ["HTTP 500", None]
    assert done["attempts"] == 2 and done["callback_url"] == receiver.url
    # Both tries reached the receiver, signed with the shared secret, with the same body.
    assert len(receiver.requests) == 2
    bodies = receiver.verified()
    assert len(bodies) == 2 and bodies[0] == bodies[1]
    assert bodies[0] == {
        "job_id": job["id"],
        "state": "succeeded",
        "status": "succeeded",
        "error": None,
        "job_url": f"http://regtree.test/v1/jobs/{job['id']}",
        "result_url": f"http://regtree.test/v1/jobs/{job['id']}/result",
        "finished_at": bodies[0]["finished_at"],
    }
    assert [r.headers["x-regtree-attempt"] for r in receiver.requests] == ["1", "2"]
    assert {r.headers["x-regtree-delivery"] for r in receiver.requests} == {str(job["id"])}
    # A receiver with another secret, or a tampered body, does not verify.
    first = receiver.requests[0]
    stamp, signature = first.headers["x-regtree-timestamp"], first.headers["x-regtree-signature"]
    assert not callbacks.verify("other", first.body, timestamp=stamp, signature=signature)
    tampered = first.body.replace(b"succeeded", b"failed")
    assert not callbacks.verify(SECRET, tampered, timestamp=stamp, signature=signature)


def test_callback_of_a_job_cancelled_while_queued_survives_a_restart(
    make_service: Callable[..., Service], receiver: Receiver
) -> None:
    """No worker runs when the job is cancelled: the delivery waits in the database, and a
    worker started later (another process) delivers it."""
    svc = make_service(workers=0, env=CALLBACK_ENV).start()
    with svc.client() as client:
        cid, ids = _collection(client)
        job = submit_job(client, cid, ids[0], callback_url=receiver.url)
        waiting = client.get(f"/v1/jobs/{job['id']}/deliveries").json()
        assert waiting["state"] == "waiting" and waiting["items"] == []
        cancelled = client.post(f"/v1/jobs/{job['id']}/cancel").json()
        assert cancelled["outcome"] == "cancelled"
        pending = client.get(f"/v1/jobs/{job['id']}/deliveries").json()
        assert pending["state"] == "pending" and pending["attempts"] == 0
    svc.stop()
    svc.launch()
    svc.start_worker()  # the database is migrated already: both start together
    svc.wait_healthy()
    with svc.client() as client:
        done = _deliveries(client, job["id"], lambda d: d["state"] == "delivered")
    assert done["attempts"] == 1
    (body,) = receiver.verified()
    assert body["state"] == "cancelled" and body["status"] == "cancelled"
    assert body["result_url"] is None


def test_a_slow_receiver_does_not_hold_up_the_next_job(
    make_service: Callable[..., Service], receiver: Receiver
) -> None:
    receiver.hold.set()
    svc = make_service(env={**CALLBACK_ENV, "REGTREE_CALLBACK_TIMEOUT_SECONDS": "120"}).start()
    with svc.client() as client:
        cid, ids = _collection(client)
        first = submit_job(client, cid, ids[0], method="direct", callback_url=receiver.url)
        assert receiver.arrived.wait(60)  # its callback is in flight, held by the receiver
        second = submit_job(client, cid, ids[0], method="direct")
        assert wait_job(client, second["id"])["status"] == "succeeded"
        assert not receiver.release.is_set()
        receiver.release.set()
        done = _deliveries(client, first["id"], lambda d: d["state"] == "delivered")
    assert done["attempts"] == 1


def test_callbacks_give_up_after_max_attempts_cli_and_client(
    make_service: Callable[..., Service], receiver: Receiver
) -> None:
    """Started with ``regtree run --callback-url``, read back with the Python client."""
    receiver.statuses = [503, 500, 502]
    svc = make_service(env=CALLBACK_ENV).start()
    with svc.client() as client:
        cid, ids = _collection(client)
    env = {k: v for k, v in os.environ.items() if not k.startswith("REGTREE_")}
    env.update(REGTREE_URL=svc.base_url, PYTHONPATH=str(REPO))
    run = subprocess.run(
        [sys.executable, "-m", "service.cli", "run", "--collection", str(cid), "--model",
         str(ids[0]), "--method", "direct", "--callback-url", receiver.url, "-q"],
        env=env, capture_output=True, text=True, timeout=120,
    )
    assert run.returncode == 0, run.stderr
    job_id = int(run.stdout.strip())
    with RegtreeClient(svc.base_url) as rt:
        assert rt.get_job(job_id).raw["callback_url"] == receiver.url
        deadline = time.monotonic() + 60
        while (done := rt.deliveries(job_id))["state"] != "failed":
            assert time.monotonic() < deadline, done
            time.sleep(0.1)
    assert [a["status_code"] for a in done["items"]] == [503, 500, 502]
    assert done["attempts"] == 3 == done["max_attempts"] and done["next_attempt_at"] is None
    assert len(receiver.requests) == 3 and len(receiver.verified()) == 3


def test_callback_hosts_outside_the_setting_are_refused(
    make_service: Callable[..., Service],
) -> None:
    svc = make_service(workers=0, env=CALLBACK_ENV).launch()
    bare = make_service(workers=0).launch()  # no secret, no allowed hosts
    svc.wait_healthy()
    bare.wait_healthy()
    with svc.client() as client, bare.client() as other:
        cid, ids = _collection(client)
        for url, words in [
            ("http://evil.example/hook", "not allowed"),
            ("http://127.0.0.2/hook", "not allowed"),
            ("ftp://127.0.0.1/hook", "http or https"),
            ("http://user:pw@127.0.0.1/hook", "user name"),
        ]:
            response = client.post(
                "/v1/jobs",
                json={"collection_id": cid, "model_shape_id": ids[0], "callback_url": url},
            )
            problem = assert_problem(response, 422)
            assert problem["type"] == "/problems/callback-refused" and words in problem["detail"]
        assert client.get("/v1/jobs").json()["total"] == 0  # nothing was queued
        ocid, oids = _collection(other)
        problem = assert_problem(
            other.post(
                "/v1/jobs",
                json={
                    "collection_id": ocid,
                    "model_shape_id": oids[0],
                    "callback_url": "http://127.0.0.1/hook",
                },
            ),
            422,
        )
        assert "callback_secret" in problem["detail"]
        none = other.get(f"/v1/jobs/{submit_job(other, ocid, oids[0])['id']}/deliveries")
        assert none.json()["state"] == "none"


# --- the rules on their own ---------------------------------------------------------------


def test_signature_and_replay_window() -> None:
    body = b'{"job_id":1}'
    now = 1_767_268_800
    signature = callbacks.sign(SECRET, now, body)
    assert signature.startswith("sha256=") and len(signature) == 7 + 64
    ok = {"timestamp": str(now), "signature": signature}
    assert callbacks.verify(SECRET, body, **ok, now=now + 10)
    assert not callbacks.verify(SECRET, body, **ok, now=now + 301)  # too old: a replay
    # The timestamp is signed too: moving it forward breaks the signature.
    moved = {"timestamp": str(now + 400), "signature": signature}
    assert not callbacks.verify(SECRET, body, **moved, now=now + 400)
    assert not callbacks.verify(SECRET, body, timestamp=None, signature=signature, now=now)
    assert not callbacks.verify(SECRET, body, timestamp="x", signature=signature, now=now)


@pytest.mark.parametrize(
    ("url", "allowed"),
    [
        ("https://hooks.example.org/a", True),
        ("https://a.b.example.net/x", True),
        ("https://example.net/x", False),  # "*.example.net" is its subdomains only
        ("http://127.0.0.1:8080/x", True),
        ("http://127.0.0.1:8081/x", False),
        ("http://[::1]:9000/x", True),
        ("http://HOOKS.example.org/a", True),
        ("http://hooks.example.org.evil.test/a", False),
    ],
)
def test_allowed_hosts(url: str, allowed: bool, tmp_path: Path) -> None:
    settings = Settings(
        database_url=f"sqlite:///{tmp_path / 'x.sqlite'}",
        callback_secret=SECRET,  # type: ignore[arg-type]
        callback_allowed_hosts="hooks.example.org, *.example.net, 127.0.0.1:8080, [::1]:9000",
    )
    if allowed:
        assert callbacks.check_url(url, settings) == url
    else:
        with pytest.raises(ValueError, match="not allowed"):
            callbacks.check_url(url, settings)
