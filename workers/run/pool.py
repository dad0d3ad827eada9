"""Shards on several cores of this machine: one worker process per core.

Shards are independent, so the natural way to use N cores is N processes, each running whole
shards on one torch thread.  Threads in one process would share the GIL with the per-harvest
Python bookkeeping of every shard and stopped scaling at about 1.1-1.4x on two cores; processes
share nothing but the tallies they send back.  The result is bitwise the same as running the
shards one after another here (a shard is a pure function of the spec and its index and the merge
sums in shard order).

Processes are started with the "spawn" method (no fork of a process holding torch's thread pools)
and live as long as the pool, so each compiles the walk once (from inductor's on-disk cache after
the first process) and keeps it for every shard it runs.
"""

from __future__ import annotations

import multiprocessing as mp
import resource
import threading
import time
from collections import deque
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Callable, Iterable, Iterator, TypeVar

import torch

from schema import SimulationSpec, parse_spec

from .cores import default_workers
from .shard import run_shard
from workers.fold.tally import ShardTally

__all__ = ["ShardPool", "default_workers", "in_order"]

T = TypeVar("T")
R = TypeVar("R")


def in_order(submit: Callable[[T], Future], items: Iterable[T], window: int) -> Iterator:
    """Results of submit(item) for each item, in item order, at most ``window`` submitted and not
    yet yielded. Items are drawn from ``items`` only when there is room, so a lazy iterable can
    look at what was yielded before deciding what comes next (a fold skipping shards)."""
    pending: deque[Future] = deque()
    for item in items:
        pending.append(submit(item))
        if len(pending) >= window:
            yield pending.popleft().result()
    while pending:
        yield pending.popleft().result()


_progress_queue = None  # set in each worker process by _init_worker


def _init_worker(progress_queue, warm_spec: dict | None, ready) -> None:
    global _progress_queue
    _progress_queue = progress_queue
    torch.set_num_threads(1)
    if warm_spec is not None:
        run_shard(parse_spec(warm_spec), 0)
    ready.release()


def _report(n: int) -> None:
    _progress_queue.put(n)


def _run(spec_doc: dict, index: int, report: bool, members: tuple[float, ...] = ()) -> bytes:
    spec = parse_spec(spec_doc)
    c0 = time.thread_time()
    tally = run_shard(spec, index, progress=_report if report else None, members=members)
    tally.info["cpu_s"] = time.thread_time() - c0
    tally.info["maxrss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return tally.to_bytes()


class ShardPool:
    """`workers` processes running shards; use as a context manager.

    warm_spec, if given, is run (shard 0) by every process as it starts, so compilation is done
    before the first real shard (the benchmark uses this to keep compile time out of its figures).
    As with any "spawn" pool, a script that creates one must guard its top level with
    ``if __name__ == "__main__":`` (each worker imports the script's main module).
    """

    def __init__(self, workers: int, warm_spec: SimulationSpec | None = None):
        self.workers = workers
        ctx = mp.get_context("spawn")
        self._queue = ctx.SimpleQueue()
        ready = ctx.Semaphore(0)  # released by each process once initialised (and warmed up)
        warm = warm_spec.model_dump(mode="json") if warm_spec is not None else None
        self._pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker, initargs=(self._queue, warm, ready))
        if warm_spec is not None:
            # Start every process now (one task each: a spawn pool starts a process per task
            # while none is idle) and wait until each has warmed up; any one finishing the
            # tasks does not mean the others are ready.
            tasks = [self._pool.submit(time.sleep, 0.0) for _ in range(workers)]
            for _ in range(workers):
                while not ready.acquire(timeout=1.0):
                    failed = [t for t in tasks if t.done() and t.exception() is not None]
                    if failed:
                        raise failed[0].exception()

    def __enter__(self) -> "ShardPool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

    def run(self, spec: SimulationSpec, indices: Iterable[int], progress: Callable[[int], None] | None = None) -> list[ShardTally]:
        """run_shard of each index on the pool's processes; the tallies in the order of indices.

        progress, if given, is called here (in this process) with photon counts as they finish.
        The tallies' info gains "cpu_s", the CPU time of the shard in its process, and
        "maxrss_mib", that process's memory peak so far.
        """
        indices = list(indices)
        return list(self.imap(((spec, i) for i in indices), progress, window=max(1, len(indices))))

    def imap(self, items: Iterable[tuple[SimulationSpec, int]], progress: Callable[[int], None] | None = None,
             window: int | None = None) -> Iterator[ShardTally]:
        """run_shard(spec, index[, members=...]) of each item (spec, index) or (spec, index,
        member albedos), in item order, with at most ``window`` (default
        two per process) submitted ahead of the one being yielded (see :func:`in_order`)."""
        last: list = [None, None]  # the last spec and its JSON form (a sweep's media come in runs)

        def submit(item: tuple) -> Future:
            spec, index, *members = item  # (spec, index) or (spec, index, member albedos)
            if last[0] is not spec:
                last[:] = [spec, spec.model_dump(mode="json")]
            return self._pool.submit(_run, last[1], index, progress is not None, tuple(members[0]) if members else ())

        results = in_order(submit, items, window or 2 * self.workers)
        if progress is None:
            for data in results:
                yield ShardTally.from_bytes(data)
            return
        stop = threading.Event()
        drain = threading.Thread(target=self._drain, args=(progress, stop), daemon=True)
        drain.start()
        try:
            for data in results:
                yield ShardTally.from_bytes(data)
        finally:
            stop.set()
            drain.join()

    def _drain(self, progress: Callable[[int], None], stop: threading.Event) -> None:
        """Relay the workers' photon counts until stop is set and nothing is left."""
        while not (self._queue.empty() and stop.is_set()):
            if self._queue.empty():
                time.sleep(0.05)
            else:
                progress(self._queue.get())
