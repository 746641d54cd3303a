"""Query handlers that take long run on worker threads, off Zenoh's callback thread.

Zenoh calls a queryable's callback on one of its own threads; a plan (seconds with a large
budget) or a time parameterisation running there holds that thread and, in Python, the GIL
that every other callback of the process needs. `RequestWorkers` takes the query, queues it
and returns at once; a fixed number of worker threads answer queued queries in arrival order.
The queue is bounded: when it is full the query is answered at once with `BUSY` (a client may
retry, or ask another replica) instead of waiting behind requests that may take minutes.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable

import zenoh

from robonav.pipeline.wire.codes import ErrorCode
from robonav.services.common import answer_query, reply_error

log = logging.getLogger("robonav")

WorkerHandler = Callable[[zenoh.Query, int], None]
"""Answers one query; the int is the index of the worker thread running it (0 … workers-1),
for services that keep state per worker (the planner keeps a collision world per worker)."""


class RequestWorkers:
    """`workers` threads answering the queries `callback` queues, at most `queue_size` waiting."""

    def __init__(self, name: str, handler: WorkerHandler, *, workers: int, queue_size: int) -> None:
        if workers < 1 or queue_size < 1:
            raise ValueError(f"{name}: workers and queue_size must be >= 1, got {workers} and {queue_size}")
        self.name = name
        self.workers = workers
        self.queue_size = queue_size
        self._handler = handler
        self._queue: queue.Queue[zenoh.Query | None] = queue.Queue(maxsize=queue_size)
        self._closed = threading.Event()
        self._lock = threading.Lock()
        self.refused = 0
        """Queries answered BUSY so far."""
        self._threads = [threading.Thread(target=self._run, args=(i,), name=f"{name}-worker-{i}", daemon=True)
                         for i in range(workers)]
        for thread in self._threads:
            thread.start()

    def callback(self, query: zenoh.Query) -> None:
        """The queryable's callback: queue `query`, or answer BUSY at once when the queue is full."""
        accepted = False
        if not self._closed.is_set():
            try:
                self._queue.put_nowait(query)
                accepted = True
            except queue.Full:
                pass
        if not accepted:
            with self._lock:
                self.refused += 1
            self._refuse(query)

    def _refuse(self, query: zenoh.Query) -> None:
        why = "is stopping" if self._closed.is_set() else (
            f"has {self.workers} busy worker(s) and {self.queue_size} request(s) waiting")
        try:
            reply_error(query, ErrorCode.BUSY, f"{self.name} {why}; try again later",
                        {"workers": self.workers, "queue_size": self.queue_size})
        except Exception:
            log.exception("%s: could not send a BUSY reply", self.name)
        finally:
            query.drop()

    def _run(self, worker: int) -> None:
        while True:
            query = self._queue.get()
            if query is None:
                return
            answer_query(query, lambda q: self._handler(q, worker), self.name)

    def close(self, timeout_s: float = 5.0) -> None:
        """Refuse new queries, answer the waiting ones BUSY, and wait up to `timeout_s` in all for
        the running ones (worker threads are daemons: a plan that does not end in time is abandoned)."""
        self._closed.set()
        while True:
            try:
                query = self._queue.get_nowait()
            except queue.Empty:
                break
            if query is not None:
                self._refuse(query)
        for _ in self._threads:
            try:
                self._queue.put(None, timeout=timeout_s)
            except queue.Full:
                break
        deadline = time.monotonic() + timeout_s  # one budget for all: a close must end in time
        for thread in self._threads:
            thread.join(timeout=max(0.0, deadline - time.monotonic()))
