"""Client pieces that need no server: SSE parsing, error mapping, NPY bodies, request shapes.

The transport-level checks use ``httpx.MockTransport`` so they see the exact request the
client would put on the wire; the live-server checks are in ``test_client.py``.
"""

from __future__ import annotations

import asyncio
import json

import httpx
import numpy as np
import pytest
from hktex_client import (
    AsyncClient,
    Client,
    Conflict,
    HKTexAPIError,
    JobFailed,
    NotFound,
    PayloadTooLarge,
    ServerError,
    Unauthorized,
    ValidationFailed,
    WaitTimeout,
    from_npy_bytes,
    to_npy_bytes,
)
from hktex_client.sse import iter_events


def test_sse_parser_follows_the_whatwg_examples() -> None:
    # The examples of the HTML standard's "server-sent events" section, written out.
    stream = (
        ": keep-alive comment\n"
        "data: first\n"
        "data: second\n"
        "\n"
        "event: progress\n"
        "id: 7\n"
        'data: {"step": 3}\n'
        "\n"
        "data:no-space\n"
        "\n"
        "retry: 1500\n"
        "data:  two spaces keep one\n"
        "\n"
        "data: unterminated at end of stream"
    )
    events = list(iter_events(stream.split("\n")))
    assert [e.event for e in events] == ["message", "progress", "message", "message", "message"]
    assert events[0].data == "first\nsecond"
    assert events[1].id == "7" and events[1].json() == {"step": 3}
    assert events[2].data == "no-space"
    assert events[3].data == " two spaces keep one" and events[3].retry == 1500
    assert events[4].data == "unterminated at end of stream"


def test_sse_handles_crlf_lines() -> None:
    events = list(iter_events(["data: a\r", "\r", "data: b\r", ""]))
    assert [e.data for e in events] == ["a", "b"]


@pytest.mark.parametrize(
    ("status", "cls"),
    [
        (401, Unauthorized),
        (404, NotFound),
        (409, Conflict),
        (413, PayloadTooLarge),
        (422, ValidationFailed),
        (500, ServerError),
        (418, HKTexAPIError),
    ],
)
def test_error_answers_become_typed_errors_with_the_reason(status: int, cls: type) -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(status, json={"detail": "mesh has 3 components"})

    with Client("http://hktex.test", transport=httpx.MockTransport(handler)) as client:
        with pytest.raises(cls) as info:
            client.get_mesh("abc")
    assert info.value.status == status
    assert info.value.reason == "mesh has 3 components"
    assert "abc" in info.value.url


def test_fastapi_validation_lists_are_rendered_as_one_line() -> None:
    detail = [
        {"loc": ["body", "params", "steps"], "msg": "Input should be >= 0", "type": "x"},
        {"loc": ["body", "mesh_id"], "msg": "Field required", "type": "y"},
    ]

    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(422, json={"detail": detail})

    with Client("http://hktex.test", transport=httpx.MockTransport(handler)) as client:
        with pytest.raises(ValidationFailed) as info:
            client.fit_uv("m1", steps=-1)
    assert info.value.reason == "params.steps: Input should be >= 0; mesh_id: Field required"
    assert info.value.detail == detail


def test_non_json_error_body_keeps_its_text() -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(502, text="Bad Gateway from proxy")

    with Client("http://hktex.test", transport=httpx.MockTransport(handler)) as client:
        with pytest.raises(ServerError, match="Bad Gateway from proxy"):
            client.health()


def test_npy_round_trip_is_exact_and_refuses_pickles() -> None:
    rng = np.random.default_rng(0)
    for arr in (rng.random((5, 3)), rng.integers(0, 9, 7).astype(np.int32), np.zeros((0, 3))):
        back = from_npy_bytes(to_npy_bytes(arr))
        assert back.dtype == arr.dtype and np.array_equal(back, arr)
    big_endian = np.arange(4, dtype=">f8")
    assert from_npy_bytes(to_npy_bytes(big_endian)).dtype.byteorder in ("<", "=")
    with pytest.raises(TypeError):
        to_npy_bytes(np.array([{"a": 1}], dtype=object))
    import io

    buf = io.BytesIO()
    np.save(buf, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError):
        from_npy_bytes(buf.getvalue())


def test_albedo_sends_npy_face_rows_and_reads_npy_colors() -> None:
    seen: dict = {}
    faces = np.array([0, 5, 2])
    bary = np.array([[1, 0, 0], [0.2, 0.3, 0.5], [0.1, 0.1, 0.8]])

    def handler(request: httpx.Request) -> httpx.Response:
        seen["type"] = request.headers["content-type"]
        seen["accept"] = request.headers["accept"]
        seen["kind"] = request.url.params.get("kind")
        rows = from_npy_bytes(request.content)
        seen["rows"] = rows
        colors = np.stack([rows[:, 0] / 10, rows[:, 1], rows[:, 3]], 1).astype(np.float32)
        return httpx.Response(
            200, content=to_npy_bytes(colors), headers={"content-type": "application/x-npy"}
        )

    with Client("http://hktex.test", transport=httpx.MockTransport(handler)) as client:
        colors = client.albedo("ks1", face_ids=faces, barycentrics=bary)
    assert seen["type"] == seen["accept"] == "application/x-npy"
    assert seen["kind"] == "faces"
    np.testing.assert_array_equal(seen["rows"][:, 0], faces)
    np.testing.assert_array_equal(seen["rows"][:, 1:], bary)
    np.testing.assert_allclose(colors[:, 0], faces / 10)
    np.testing.assert_allclose(colors[:, 2], bary[:, 2])


def test_albedo_chunks_split_and_reassemble_in_order() -> None:
    sizes: list[int] = []

    def handler(request: httpx.Request) -> httpx.Response:
        body = json.loads(request.content)
        pts = np.asarray(body["points"])
        sizes.append(len(pts))
        return httpx.Response(200, json={"count": len(pts), "colors": pts.tolist()})

    pts = np.arange(30, dtype=float).reshape(10, 3)
    with Client("http://hktex.test", transport=httpx.MockTransport(handler)) as client:
        colors = client.albedo("ks1", points=pts, binary=False, chunk_size=4)
    assert sizes == [4, 4, 2]
    np.testing.assert_allclose(colors, pts)


def test_albedo_rejects_ambiguous_queries_before_sending() -> None:
    with Client("http://hktex.test", transport=httpx.MockTransport(lambda r: None)) as client:
        with pytest.raises(ValueError):
            client.albedo("ks1")
        with pytest.raises(ValueError):
            client.albedo("ks1", face_ids=[1], barycentrics=[[1, 0, 0]], points=[[0, 0, 0]])
        with pytest.raises(ValueError):
            client.albedo("ks1", face_ids=[1, 2], barycentrics=[[1, 0, 0]])


def _job(state: str, step: int = 0) -> dict:
    return {"id": "j1", "task": "fit_uv", "state": state, "progress": {"step": step, "total": 4}}


def test_wait_polls_until_final_and_raises_on_failure() -> None:
    states = iter(["queued", "running", "running", "failed"])

    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(200, json={**_job(next(states)), "error": "out of memory"})

    with Client("http://hktex.test", transport=httpx.MockTransport(handler)) as client:
        with pytest.raises(JobFailed, match="out of memory"):
            client.wait("j1", timeout=5, poll=0.001)


def test_wait_times_out_with_the_last_record() -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(200, json=_job("running", 2))

    with Client("http://hktex.test", transport=httpx.MockTransport(handler)) as client:
        with pytest.raises(WaitTimeout) as info:
            client.wait("j1", timeout=0.05, poll=0.01)
    assert info.value.job.progress.step == 2


def test_async_client_streams_events_until_the_final_state() -> None:
    body = "".join(
        f"event: progress\ndata: {json.dumps(_job(s, i))}\n\n"
        for i, s in enumerate(["running", "running", "succeeded", "running"])
    )

    def handler(request: httpx.Request) -> httpx.Response:
        assert request.url.path == "/v1/jobs/j1/events"
        return httpx.Response(200, text=body, headers={"content-type": "text/event-stream"})

    async def main() -> list[str]:
        async with AsyncClient("http://hktex.test", transport=httpx.MockTransport(handler)) as c:
            return [e.json()["state"] async for e in c.stream_events("j1")]

    assert asyncio.run(main()) == ["running", "running", "succeeded"]


def test_token_is_sent_as_bearer() -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        assert request.headers["authorization"] == "Bearer s3cret"
        return httpx.Response(200, json={"status": "ok"})

    with Client("http://hktex.test", token="s3cret", transport=httpx.MockTransport(handler)) as c:
        assert c.health().status == "ok"


@pytest.mark.parametrize(
    "name",
    [
        "MeshRecord",
        "SpectraRecord",
        "JobProgress",
        "JobResult",
        "JobRecord",
        "KernelSetRecord",
        "ViewsRecord",
        "Health",
        "QueueDepth",
        "Info",
    ],
)
def test_client_records_mirror_the_server_schemas(name: str) -> None:
    # The client cannot import the server (it must stay light), so its records are declared
    # twice; this is the check that the two declarations name the same fields.
    from hktex_client import models as client_models
    from hktex_server.api import schemas as server_schemas

    ours = set(getattr(client_models, name).model_fields)
    theirs = set(getattr(server_schemas, name).model_fields)
    assert ours == theirs, f"client lacks {theirs - ours}, has extra {ours - theirs}"


def test_client_records_parse_a_server_record() -> None:
    from hktex_client.models import JobRecord as ClientJob
    from hktex_server.api import schemas as server_schemas

    record = server_schemas.JobRecord(
        id="job_1",
        task="fit_uv",
        state="running",
        created_at=1.0,
        progress=server_schemas.JobProgress(step=3, total=10, loss=0.5, kernel_count=7),
        result=server_schemas.JobResult(kernelset_id="kst_1"),
    )
    job = ClientJob.model_validate_json(record.model_dump_json())
    assert job.progress.fraction == 0.3 and job.kernelset_id == "kst_1" and not job.done


def test_wait_keeps_polling_through_a_restarting_service() -> None:
    answers = iter(
        [
            httpx.ConnectError("connection refused"),
            httpx.Response(503, json={"detail": "starting"}),
            httpx.Response(200, json=_job("running", 1)),
            httpx.Response(200, json=_job("succeeded", 4)),
        ]
    )

    def handler(request: httpx.Request) -> httpx.Response:
        answer = next(answers)
        if isinstance(answer, Exception):
            raise answer
        return answer

    with Client("http://hktex.test", transport=httpx.MockTransport(handler)) as client:
        assert client.wait("j1", timeout=5, poll=0.001).state == "succeeded"


def test_wait_gives_up_on_a_dead_service_at_the_deadline() -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        raise httpx.ConnectError("connection refused")

    with Client("http://hktex.test", transport=httpx.MockTransport(handler)) as client:
        with pytest.raises(httpx.ConnectError):
            client.wait("j1", timeout=0.05, poll=0.01)
