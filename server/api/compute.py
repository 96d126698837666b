"""Request-time heavy work (albedo queries, renders, views decoding, the viewer's bakes) in a
bounded pool of worker processes.

Why processes: a render or a big query on an API thread cannot be stopped (Python has no
thread kill), holds the GIL against the event loop, and leaves its memory in the API process
(a 256x256 spp=255 render grew the server from 0.6 to 6-8 GB and kept running after its
client left). In a worker process it can be killed, and its memory goes with it.

- ``compute_workers`` long-lived workers (default: the cores this process may use), each
  forked from the forkserver with the engine preloaded (``compute_child``), each with its own
  warm kernel sets, ``compute_threads`` CPU threads each: queries of one kernel set run in
  parallel up to the workers.
- Fair share: requests wait in one queue per owner and workers take from the owners in turn
  (round-robin), so one owner's burst delays another owner's request by at most one request
  per worker; an owner may hold ``max_queued_per_owner`` waiting requests (then 429).
- Budgets: ``compute_timeout_seconds`` of run time (then the worker is killed: 503) and
  ``compute_memory_bytes`` of address space per request (``RLIMIT_AS`` in the worker: 422).
- A request whose client disconnects is dropped from the queue, or its worker is killed;
  identical requests may share one task (``share``), cancelled when the last caller goes.
- ``abort`` (on SIGTERM) fails everything at once with 503, so in-flight requests do not hold
  up the server's exit; ``close`` kills the workers.

One driver thread per worker moves requests to it and watches the clock and the cancel flag;
the event loop only awaits a future.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

from fastapi import HTTPException, Request
from hktex_server.settings import Settings

log = logging.getLogger("hktex.compute")

DISCONNECT_POLL_SECONDS = 0.1


class ComputeError(HTTPException):
    """A compute request that failed with a status for the caller."""


class Cancelled(Exception):
    """The request was cancelled (its client went away)."""


@dataclass(eq=False)
class ComputeTask:
    owner: str
    kind: str
    payload: dict[str, Any]
    timeout: float
    memory: int
    future: Future = field(default_factory=Future)
    cancelled: threading.Event = field(default_factory=threading.Event)
    queued_at: float = field(default_factory=time.monotonic)
    #: called on the driver thread once the task has run, after its worker answered or was
    #: killed (so nothing still writes): removes what a killed worker left half-written
    cleanup: Callable[[], None] | None = None

    def cancel(self) -> None:
        self.cancelled.set()
        if not self.future.done():
            self.future.set_exception(Cancelled())


class FairQueue:
    """Waiting tasks, one FIFO per owner, served round-robin across owners."""

    def __init__(self, max_per_owner: int) -> None:
        self.max_per_owner = max_per_owner
        self._queues: OrderedDict[str, deque[ComputeTask]] = OrderedDict()
        self._cond = threading.Condition()
        self._closed = False

    def put(self, task: ComputeTask) -> None:
        with self._cond:
            if self._closed:
                raise ComputeError(503, detail="the service is shutting down")
            q = self._queues.setdefault(task.owner, deque())
            waiting = sum(1 for t in q if not t.cancelled.is_set())
            if waiting >= self.max_per_owner:
                raise ComputeError(
                    429,
                    detail=f"{waiting} requests of yours are already waiting (limit "
                    f"{self.max_per_owner}); retry when some have finished",
                    headers={"Retry-After": "1"},
                )
            q.append(task)
            self._cond.notify()

    def get(self, timeout: float) -> ComputeTask | None:
        """The next live task of the owner whose turn it is, or None after ``timeout``."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                while self._queues:
                    owner, q = next(iter(self._queues.items()))
                    task = q.popleft()
                    if q:
                        self._queues.move_to_end(owner)  # the next owner's turn
                    else:
                        del self._queues[owner]
                    if not task.cancelled.is_set():
                        return task
                left = deadline - time.monotonic()
                if self._closed or left <= 0:
                    return None
                self._cond.wait(left)

    def drain(self) -> list[ComputeTask]:
        with self._cond:
            self._closed = True
            tasks = [t for q in self._queues.values() for t in q]
            self._queues.clear()
            self._cond.notify_all()
            return tasks

    def depth(self) -> int:
        with self._cond:
            return sum(len(q) for q in self._queues.values())


class _Slot:
    """One worker process and the driver thread that feeds it."""

    def __init__(self, pool: ComputePool, index: int) -> None:
        self.pool, self.index = pool, index
        self.proc: Any = None
        self.conn: Any = None
        self.task: ComputeTask | None = None
        self.restarts = 0
        self.thread = threading.Thread(
            target=self._drive, name=f"hktex-compute-{index}", daemon=True
        )

    # -------------------------------------------------------- the worker process

    def _start(self) -> None:
        from hktex_server.api import compute_child, validation

        ctx = validation.context()
        parent, child = ctx.Pipe(duplex=True)
        st = self.pool.settings
        proc = ctx.Process(
            target=compute_child.main,
            args=(
                child,
                st.compute_threads,
                st.query_cache_size,
                st.compute_recycle_bytes,
                st.compute_nice,
            ),
            name=f"hktex-compute-{self.index}",
            daemon=True,
        )
        proc.start()
        child.close()
        self.proc, self.conn = proc, parent

    def _stop(self) -> None:
        proc, conn = self.proc, self.conn
        self.proc = self.conn = None
        if proc is not None and proc.is_alive():
            proc.kill()
        if conn is not None:
            conn.close()
        if proc is not None:
            proc.join(5)

    def alive(self) -> bool:
        return self.proc is not None and self.proc.is_alive()

    # -------------------------------------------------------- the driver

    def _drive(self) -> None:
        pool = self.pool
        while not pool.closing.is_set():
            if not self.alive():
                self._stop()
                try:
                    self._start()
                except Exception:  # noqa: BLE001 - try again in a moment; requests wait
                    log.exception("compute worker %d failed to start", self.index)
                    pool.closing.wait(1.0)
                    continue
            task = pool.queue.get(timeout=0.5)
            if task is None:
                continue
            self.task = task
            try:
                self._run(task)
            finally:
                self.task = None
                if task.cleanup is not None:
                    try:
                        task.cleanup()
                    except Exception:  # noqa: BLE001 - a leftover temp file is not fatal
                        log.exception("compute cleanup of a %s request failed", task.kind)
        self._stop()

    def _run(self, task: ComputeTask) -> None:
        pool = self.pool
        try:
            self.conn.send((task.kind, task.payload, task.memory))
        except (BrokenPipeError, OSError):
            self._fail(task, 503, "the compute worker was not available; retry")
            self._stop()
            return
        deadline = time.monotonic() + task.timeout
        while True:
            try:
                ready = self.conn.poll(0.05)
            except (EOFError, OSError):
                ready = True
            if ready:
                try:
                    reply = self.conn.recv()
                except (EOFError, OSError):
                    code = self.proc.exitcode if self.proc is not None else None
                    self._stop()
                    self._fail(
                        task,
                        503,
                        f"the compute worker died while running this request (exit code "
                        f"{code}); it may have needed more than its "
                        f"{task.memory // 2**20} MiB memory budget",
                    )
                    return
                if reply[-1]:  # the worker retires (it grew big): a fresh one next
                    self._stop()
                if reply[0] == "ok":
                    if not task.future.done():
                        task.future.set_result(reply[1])
                else:
                    self._fail(task, reply[1], reply[2])
                return
            if task.cancelled.is_set() or pool.closing.is_set():
                self._stop()  # killed: its memory and CPU go with it
                self._fail(task, 503, "cancelled")
                return
            if time.monotonic() > deadline:
                self._stop()
                self._fail(
                    task,
                    503,
                    f"the request ran past its time budget of {task.timeout:g} s and was "
                    "stopped; ask for fewer points, pixels or samples",
                    retry=False,
                )
                return

    @staticmethod
    def _fail(task: ComputeTask, status: int, detail: str, retry: bool = True) -> None:
        if task.future.done():
            return
        headers = {"Retry-After": "1"} if status == 503 and retry else None
        task.future.set_exception(ComputeError(status, detail=detail, headers=headers))


@dataclass(eq=False)
class _Shared:
    """A task several identical requests wait on; cancelled when the last of them leaves."""

    task: ComputeTask
    waiters: int = 1


class ComputePool:
    """The pool; ``start`` at service start, ``await run(...)`` per request, ``close`` at exit."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.size = settings.compute_workers_resolved()
        self.queue = FairQueue(settings.max_queued_per_owner)
        self.closing = threading.Event()
        self.slots = [_Slot(self, i) for i in range(self.size)]
        self._shared: dict[str, _Shared] = {}
        self._shared_lock = threading.Lock()

    def start(self) -> None:
        for slot in self.slots:
            slot.thread.start()

    def submit(
        self,
        owner: str,
        kind: str,
        payload: dict[str, Any],
        cleanup: Callable[[], None] | None = None,
    ) -> ComputeTask:
        st = self.settings
        task = ComputeTask(
            owner,
            kind,
            payload,
            st.compute_timeout_seconds,
            st.compute_memory_bytes,
            cleanup=cleanup,
        )
        if self.closing.is_set():
            raise ComputeError(503, detail="the service is shutting down")
        self.queue.put(task)
        return task

    def _join(self, key: str, owner: str, kind: str, payload: dict, cleanup) -> _Shared:
        """The running task for ``key``, or a new one submitted for this caller."""
        with self._shared_lock:
            entry = self._shared.get(key)
            if entry is not None and not entry.task.future.done():
                entry.waiters += 1
                return entry
            entry = _Shared(self.submit(owner, kind, payload, cleanup))
            self._shared[key] = entry
        entry.task.future.add_done_callback(lambda _f: self._forget(key, entry))
        return entry

    def _forget(self, key: str, entry: _Shared) -> None:
        with self._shared_lock:
            if self._shared.get(key) is entry:
                del self._shared[key]

    def _leave(self, key: str, entry: _Shared) -> None:
        """One waiter went away; the last one cancels the task (its worker is killed)."""
        with self._shared_lock:
            entry.waiters -= 1
            last = entry.waiters <= 0
            if last and self._shared.get(key) is entry:
                del self._shared[key]  # a request arriving now starts afresh
        if last:
            entry.task.cancel()

    async def run(
        self,
        request: Request | None,
        owner: str,
        kind: str,
        payload: dict,
        share: str | None = None,
        cleanup: Callable[[], None] | None = None,
    ) -> Any:
        """Submit and wait; the task is cancelled (its worker killed) if the client goes.

        With ``share``, identical requests (same key) running at once wait on one task, queued
        under the first caller's owner; it is cancelled only when all its callers have gone."""
        if share is None:
            task = self.submit(owner, kind, payload, cleanup)
            leave = task.cancel
        else:
            entry = self._join(share, owner, kind, payload, cleanup)
            task = entry.task

            def leave() -> None:
                self._leave(share, entry)

        waiter = asyncio.wrap_future(task.future)
        try:
            while True:
                done, _ = await asyncio.wait({waiter}, timeout=DISCONNECT_POLL_SECONDS)
                if done:
                    try:
                        return waiter.result()
                    except Cancelled:
                        raise ComputeError(503, detail="cancelled") from None
                if request is not None and await request.is_disconnected():
                    _abandon(leave, waiter)
                    raise ComputeError(499, detail="the client went away")
        except asyncio.CancelledError:
            _abandon(leave, waiter)
            raise

    def abort(self, reason: str = "the service is shutting down") -> None:
        """Fail every waiting and running request now (503) and stop the workers: called on
        SIGTERM so in-flight renders do not hold up the exit. Safe from any thread."""
        self.closing.set()
        for task in self.queue.drain():
            _Slot._fail(task, 503, reason)
            task.cancelled.set()
        for slot in self.slots:
            task = slot.task
            if task is not None:
                _Slot._fail(task, 503, reason)

    def close(self, timeout: float = 5.0) -> None:
        self.abort()
        deadline = time.monotonic() + timeout
        for slot in self.slots:
            if slot.thread.is_alive():
                slot.thread.join(max(0.0, deadline - time.monotonic()))
        for slot in self.slots:  # a driver stuck past the deadline: kill its worker anyway
            proc = slot.proc
            if proc is not None and proc.is_alive():
                proc.kill()

    def status(self) -> dict[str, Any]:
        return {
            "workers": self.size,
            "alive": sum(1 for s in self.slots if s.alive()),
            "busy": sum(1 for s in self.slots if s.task is not None),
            "queued": self.queue.depth(),
            "pids": [s.proc.pid for s in self.slots if s.proc is not None],
        }


def _abandon(leave: Callable[[], None], waiter: asyncio.Future) -> None:
    """Leave the task (cancelling it when nobody else waits); this caller will not read its
    outcome (say so to asyncio, which would warn)."""
    waiter.add_done_callback(lambda f: f.cancelled() or f.exception())
    leave()
