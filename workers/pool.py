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
from concurrent.futures import ProcessPoolExecutor
from typing import Callable, Iterable

import torch

from schema import SimulationSpec, parse_spec

from .cores import default_workers
from .shard import run_shard
from .tally import ShardTally

__all__ = ["ShardPool", "default_workers"]


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


def _run(spec_doc: dict, index: int, report: bool) -> bytes:
    spec = parse_spec(spec_doc)
    c0 = time.thread_time()
    tally = run_shard(spec, index, progress=_report if report else None)
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
        doc = spec.model_dump(mode="json")
        futures = [self._pool.submit(_run, doc, i, progress is not None) for i in indices]
        if progress is None:
            return [ShardTally.from_bytes(f.result()) for f in futures]
        stop = threading.Event()
        drain = threading.Thread(target=self._drain, args=(progress, stop), daemon=True)
        drain.start()
        try:
            return [ShardTally.from_bytes(f.result()) for f in futures]
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
