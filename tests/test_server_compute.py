"""Queries and renders in bounded worker processes (issue 11, server/api/compute.py).

The fair queue is tested alone; the rest runs a real ``hktex serve`` on loopback with a seeded
kernel set: an abandoned big render is killed (its memory goes, a small render asked meanwhile
answers), a render past its time budget is a 503 naming the budget, and SIGTERM stops the
server within seconds while a render runs. Sizes are CI-sized versions of the issue's
(256x256 spp=255 abandoned, 32x32 within 10 s, exit within 10 s of SIGTERM).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest
from hktex_server.api.compute import ComputeError, ComputeTask, FairQueue

from tests.server_support import free_port, seed_kernelset, wait_for

pytest.importorskip("hktex_engine.kernels.query")


# ---------------------------------------------------------------- fair queue


def test_fair_queue_serves_owners_in_turn() -> None:
    q = FairQueue(max_per_owner=10)
    burst = [ComputeTask("alice", "ping", {"i": i}, 1.0, 2**30) for i in range(5)]
    for t in burst:
        q.put(t)
    bob = ComputeTask("bob", "ping", {}, 1.0, 2**30)
    q.put(bob)
    order = [q.get(0.1) for _ in range(6)]
    assert order[0] is burst[0] and order[1] is bob, "bob waits for one of alice's, not five"
    assert order[2:] == burst[1:]
    assert q.get(0.01) is None


def test_fair_queue_caps_waiting_requests_and_skips_cancelled() -> None:
    q = FairQueue(max_per_owner=2)
    a, b = (ComputeTask("alice", "ping", {}, 1.0, 2**30) for _ in range(2))
    q.put(a)
    q.put(b)
    with pytest.raises(ComputeError) as err:
        q.put(ComputeTask("alice", "ping", {}, 1.0, 2**30))
    assert err.value.status_code == 429
    q.put(ComputeTask("bob", "ping", {}, 1.0, 2**30))  # another owner is not capped by alice
    a.cancel()  # its client went away while it waited
    assert q.get(0.1).owner == "bob"  # alice's turn came first, but her head was cancelled
    assert q.get(0.1) is b
    assert q.drain() == [] and q.get(0.01) is None


# ---------------------------------------------------------------- a real server


def _tree_rss(pid: int) -> int:
    """Resident bytes of a process and all its descendants (from /proc)."""
    parents: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    parents[int(entry)] = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
    tree, frontier = {pid}, [pid]
    while frontier:
        p = frontier.pop()
        kids = [c for c, pp in parents.items() if pp == p and c not in tree]
        tree.update(kids)
        frontier += kids
    total = 0
    for p in tree:
        try:
            with open(f"/proc/{p}/statm") as f:
                total += int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
        except OSError:
            pass
    return total


class Serve:
    """``hktex serve`` as a child (own session) so the test can SIGTERM it and time the exit."""

    def __init__(self, data_dir: Path, **env: str) -> None:
        self.data_dir = data_dir
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        cmd = [sys.executable, "-m", "hktex_engine", "serve", "--port", str(self.port)]
        cmd += ["--data-dir", str(data_dir), "--workers", "0", "--log-level", "warning"]
        data_dir.mkdir(parents=True, exist_ok=True)
        self.log = (data_dir / "serve.log").open("ab")
        full_env = {**os.environ, "OMP_NUM_THREADS": "1", "HKTEX_TOKENS": "", **env}
        self.proc = subprocess.Popen(
            cmd, env=full_env, stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True
        )

        def healthy() -> bool:
            assert self.proc.poll() is None, (data_dir / "serve.log").read_text()[-2000:]
            try:
                return httpx.get(f"{self.url}/v1/health", timeout=2).status_code == 200
            except httpx.HTTPError:
                return False

        wait_for(healthy, 120, "hktex serve")

    def stop(self) -> float:
        """SIGTERM; seconds until the process exited (SIGKILL after 30 s)."""
        t0 = time.monotonic()
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
        self.log.close()
        return time.monotonic() - t0


@pytest.fixture(scope="module")
def ico_obj(tmp_path_factory) -> Path:
    from hktex_engine.evaluation.synthetic import icosphere, write_textured_obj

    v, f = icosphere(2)
    return write_textured_obj(tmp_path_factory.mktemp("compute-mesh") / "ico.obj", v, f)


def _render(url: str, ks: str, size: int, spp: int, timeout: float) -> httpx.Response:
    params = {"width": size, "height": size, "spp": spp}
    return httpx.get(f"{url}/v1/kernelsets/{ks}/render", params=params, timeout=timeout)


@pytest.mark.mitsuba
def test_abandoned_render_is_killed_and_small_render_answers(tmp_path, ico_obj) -> None:
    serve = Serve(tmp_path / "data", HKTEX_COMPUTE_WORKERS="2", HKTEX_COMPUTE_TIMEOUT_SECONDS="300")
    try:
        ids = seed_kernelset(serve.url, serve.data_dir, ico_obj)
        ks = ids["kernelset_id"]
        warm = _render(serve.url, ks, 32, 1, 120)  # mitsuba loaded in one worker
        if warm.status_code == 503 and "renderer unavailable" in warm.text:
            pytest.skip(warm.json()["detail"])
        assert warm.status_code == 200, warm.text
        baseline = _tree_rss(serve.proc.pid)
        with pytest.raises(httpx.TimeoutException):  # the client gives up on a big render
            _render(serve.url, ks, 256, 255, 3)
        t0 = time.monotonic()
        small = _render(serve.url, ks, 32, 1, 30)  # asked right after the abandonment
        took = time.monotonic() - t0
        assert small.status_code == 200 and small.content[:4] == b"\x89PNG", small.text
        assert took < 10, f"a 32x32 render took {took:.1f} s next to an abandoned big one"
        wait_for(
            lambda: _tree_rss(serve.proc.pid) < baseline + 512 * 2**20,
            20,
            "the abandoned render's memory to be returned",
        )
        # the abandoned render's worker was killed, so nothing keeps a core busy
        h = httpx.get(f"{serve.url}/v1/health", timeout=5)
        assert h.status_code == 200
    finally:
        took = serve.stop()
    assert took < 10, f"hktex serve needed {took:.1f} s to exit"


@pytest.mark.mitsuba
def test_time_budget_and_sigterm_during_a_render(tmp_path, ico_obj) -> None:
    serve = Serve(tmp_path / "data", HKTEX_COMPUTE_WORKERS="1", HKTEX_COMPUTE_TIMEOUT_SECONDS="3")
    try:
        ks = seed_kernelset(serve.url, serve.data_dir, ico_obj)["kernelset_id"]
        t0 = time.monotonic()
        r = _render(serve.url, ks, 256, 255, 60)
        if r.status_code == 503 and "renderer unavailable" in r.text:
            pytest.skip(r.json()["detail"])
        assert r.status_code == 503 and "time budget of 3 s" in r.json()["detail"], r.text
        assert time.monotonic() - t0 < 30
        ok = httpx.post(
            f"{serve.url}/v1/kernelsets/{ks}/albedo",
            json={"face_ids": [0, 1], "barycentrics": [[1, 0, 0], [0, 0.5, 0.5]]},
            timeout=60,
        )
        assert ok.status_code == 200 and ok.json()["count"] == 2, ok.text
        # SIGTERM while a render runs: the server must not wait for it
        answers: list[int] = []

        def long_render() -> None:
            try:
                answers.append(_render(serve.url, ks, 256, 255, 60).status_code)
            except httpx.HTTPError:
                answers.append(-1)

        thread = threading.Thread(target=long_render, daemon=True)
        thread.start()
        time.sleep(1.0)
    finally:
        took = serve.stop()
    assert took < 10, f"hktex serve needed {took:.1f} s to exit during a render"
    thread.join(10)
    assert answers and answers[0] in (503, -1), answers


# ---------------------------------------------------------------- views uploads: bombs


def _peak_rss(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    raise AssertionError("no VmHWM")


def _gray_png(width: int, height: int) -> bytes:
    """A valid all-black grayscale PNG, compressed row by row (never held raw in memory)."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    z = zlib.compressobj(9)
    row = b"\x00" * (width + 1)
    idat = b"".join(z.compress(row) for _ in range(height)) + z.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def test_views_bombs_are_refused_with_bounded_server_memory(tmp_path) -> None:
    import io
    import json
    import zipfile

    serve = Serve(
        tmp_path / "data",
        HKTEX_COMPUTE_WORKERS="1",
        HKTEX_MAX_UPLOAD_BYTES=str(4_000_000),
        HKTEX_MAX_ARCHIVE_BYTES=str(50_000_000),
        HKTEX_COMPUTE_MEMORY_BYTES=str(512 * 2**20),
    )
    try:
        c = httpx.Client(base_url=serve.url, timeout=120)

        def post(data: bytes) -> httpx.Response:
            return c.post("/v1/views", files={"archive": ("v.zip", data, "application/zip")})

        assert post(b"PK\x03\x04 not a zip").status_code == 422  # the compute path is warm
        baseline = _peak_rss(serve.proc.pid)
        # 1. an archive bigger than the upload limit: 413 while it streams
        assert post(os.urandom(5_000_000)).status_code == 413
        # 2. a zip bomb: 300 MB of zeros in ~300 KB, past max_archive_bytes when inflated
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
            zf.writestr("views.json", b"{}")
            with zf.open("a.bin", "w", force_zip64=True) as member:
                block = b"\0" * 2**20
                for _ in range(300):
                    member.write(block)
        assert len(buf.getvalue()) < 4_000_000
        r = post(buf.getvalue())
        assert r.status_code == 413 and "unpacks to more than" in r.json()["detail"], r.text
        # 3. a pixel bomb: a small PNG that decodes to 144 M pixels (1.7 GB as float RGB);
        # decoded in a compute worker under a 512 MiB budget: 422, the API process untouched
        png = _gray_png(12_000, 12_000)
        manifest = {
            "format": "hktex-views",
            "version": 1,
            "width": 12_000,
            "height": 12_000,
            "views": [
                {
                    "name": "v0",
                    "image": "v0.png",
                    "camera": {"fov": 40, "origin": [0, 0, 3], "target": [0, 0, 0]},
                }
            ],
        }
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
            zf.writestr("views.json", json.dumps(manifest))
            zf.writestr("v0.png", png)
        r = post(buf.getvalue())
        assert r.status_code == 422 and "memory budget" in r.json()["detail"], r.text
        grown = _peak_rss(serve.proc.pid) - baseline
        assert grown < 150 * 2**20, f"the API process peaked {grown / 2**20:.0f} MiB higher"
        assert c.get("/v1/health").status_code == 200
        c.close()
    finally:
        serve.stop()


# ---------------------------------------------------------------- the pool itself


def _pool(tmp_path, **over):
    from hktex_server.api.compute import ComputePool

    from tests.server_support import fast_settings

    settings = fast_settings(tmp_path, f"sqlite:///{tmp_path / 'p.db'}", **over)
    pool = ComputePool(settings)
    pool.start()
    wait_for(lambda: pool.status()["alive"] == pool.size, 120, "the compute workers")
    return pool


def _wait(task, timeout: float = 60):
    return task.future.result(timeout)


def test_pool_runs_in_parallel_and_serves_owners_in_turn(tmp_path) -> None:
    pool = _pool(tmp_path, compute_workers=2)
    try:
        t0 = time.monotonic()
        done: dict[int, float] = {}

        def submit(owner: str):
            task = pool.submit(owner, "ping", {"seconds": 1.0})
            task.future.add_done_callback(
                lambda _f, k=id(task): done.setdefault(k, time.monotonic() - t0)
            )
            return task

        alice = [submit("alice") for _ in range(4)]
        bob = submit("bob")
        for task in [*alice, bob]:
            _wait(task)
        # serial: 5 s; two workers: 3 s at most, and bob's one request is among the first two
        assert max(done.values()) < 4.5, done
        assert done[id(bob)] < done[id(alice[-1])] - 0.5, done
        pids = {_wait(t) for t in [*alice, bob]}
        assert len(pids) == 2, "both workers served"
    finally:
        pool.close()


def test_pool_kills_a_cancelled_or_overdue_request(tmp_path) -> None:
    pool = _pool(tmp_path, compute_workers=1, compute_timeout_seconds=1.0)
    try:
        first_pid = _wait(pool.submit("alice", "ping", {}))
        slow = pool.submit("alice", "ping", {"seconds": 5.0})
        with pytest.raises(ComputeError) as err:
            _wait(slow, 30)
        assert err.value.status_code == 503 and "time budget of 1 s" in err.value.detail
        second_pid = _wait(pool.submit("alice", "ping", {}))
        assert second_pid != first_pid, "the overdue request's worker was killed and replaced"
        task = pool.submit("alice", "ping", {"seconds": 5.0})
        time.sleep(0.5)
        t0 = time.monotonic()
        task.cancel()  # what the route does when the client disconnects
        third_pid = _wait(pool.submit("alice", "ping", {}))
        assert time.monotonic() - t0 < 4, "the cancelled request did not hold the worker"
        assert third_pid != second_pid
    finally:
        pool.close()
    assert all(not s.alive() for s in pool.slots), "close() leaves no worker behind"


class _Client:
    """What ``ComputePool.run`` asks of a request: whether its client went away."""

    def __init__(self) -> None:
        self.gone = False

    async def is_disconnected(self) -> bool:
        return self.gone


def test_pool_shared_task_ends_only_when_its_last_caller_goes(tmp_path) -> None:
    import asyncio

    pool = _pool(tmp_path, compute_workers=1)
    try:

        async def scenario():
            a, b = _Client(), _Client()
            ping = {"seconds": 1.0}
            one = asyncio.ensure_future(pool.run(a, "alice", "ping", ping, share="k"))
            two = asyncio.ensure_future(pool.run(b, "bob", "ping", ping, share="k"))
            await asyncio.sleep(0.3)
            a.gone = True  # one caller leaves: the other still gets the shared answer
            with pytest.raises(ComputeError) as err:
                await one
            assert err.value.status_code == 499
            pid = await two
            c = _Client()
            three = asyncio.ensure_future(pool.run(c, "alice", "ping", ping, share="k"))
            await asyncio.sleep(0.3)
            c.gone = True  # the only caller leaves: the task is cancelled, its worker killed
            with pytest.raises(ComputeError):
                await three
            return pid, await pool.run(None, "alice", "ping", {}, share="k")

        first, after = asyncio.run(scenario())
        assert first != after, "the last caller leaving killed the shared task's worker"
    finally:
        pool.close()
