"""The worker: claim a task, run it under a heartbeated lease, commit, repeat.

    bssrdf worker --db URL --storage URI [--once] [--max-tasks N] [--lease-seconds S]

(the command line is :mod:`service.worker_command`; ``python -m service.worker`` runs it too).
``Worker.run`` installs the signal handlers and calls ``loop``; ``loop`` alternates ``claim`` and
``process``. While a task runs, a heartbeat thread extends the lease every ``heartbeat_seconds``;
if a heartbeat finds the lease lost (expired and re-claimed, or the job cancelled) the shard is
abandoned at the next progress call and its result discarded. A finished shard's commit that
fails with a database error (a restart, a failover) is retried for up to two minutes; no database
error ends the worker (a failure it cannot record is left to the lease). SIGTERM/SIGINT: a running shard is
abandoned and its lease released (queued again, not counted as an attempt), a running merge is
finished; then the worker exits with status 0. Logs: one JSON object per line on stderr unless
stderr is a terminal.
"""

from __future__ import annotations

import json
import logging
import os
import random
import signal
import socket
import sys
import threading
import time
import uuid

from sqlalchemy.exc import DBAPIError

from schema import SimulationSpec, parse_spec
from service.datasets import DatasetStorage, JobFiles, run_merge_task
from service.settings import IDLE_BACKOFF_CAP
from service.store import JobNotFound, JobStore, Lease, LeaseLost, TaskKind
from workers.fold.finite import NonFiniteResult
from workers.run.task import run_task
from workers.walk.kernels import observe_compiles

__all__ = ["Worker", "compile_phase"]

log = logging.getLogger("bssrdf.worker")



class _Abandon(Exception):
    """Raised from the progress callback to stop a shard early (lease lost, or stopping)."""


class _CommitUnknown(Exception):
    """A finished shard's commit kept failing with database errors: whether one attempt went
    through is not known. The lease decides: if nothing was recorded it expires and the shard
    is walked again (bit-identically) by whoever claims it."""


class _Heartbeat(threading.Thread):
    """Extends a lease every ``period`` seconds until stopped; sets ``lost`` if it was lost.

    Liveness follows progress, not the process: once the task has reported progress, a gap of
    more than ``stall_seconds`` since its last report (a hung walk) stops the heartbeats, so the
    lease expires and another worker redoes the task; ``stalled`` and ``lost`` are set, and the
    walk, should it ever resume, is abandoned at its next progress call.
    """

    def __init__(self, store: JobStore, lease: Lease, lease_seconds: float, period: float, photons,
                 last_progress=None, stall_seconds: float | None = None, phase=None) -> None:
        super().__init__(name=f"heartbeat-{lease.task_id}", daemon=True)
        self.store, self.lease, self.lease_seconds, self.period = store, lease, lease_seconds, period
        self.photons = photons  # callable -> photons done so far
        self.last_progress = last_progress  # callable -> monotonic time of the last progress report, or None
        self.phase = phase  # callable -> what the task does besides walking ("compiling ..."), or None
        self.stall_seconds = stall_seconds
        self.lost = threading.Event()
        self.stalled = threading.Event()
        self._stop_event = threading.Event()
        self._wake = threading.Event()

    def _is_stalled(self) -> bool:
        if self.stall_seconds is None or self.last_progress is None:
            return False
        last = self.last_progress()
        return last is not None and time.monotonic() - last > self.stall_seconds

    def run(self) -> None:
        while True:
            self._wake.wait(self.period)  # a period, or sooner when poked (the phase changed)
            self._wake.clear()
            if self._stop_event.is_set():
                return
            if self._is_stalled():
                log.error("no progress: heartbeats stopped, the lease will expire and the task be redone elsewhere",
                          extra={"task": self.lease.task_id, "stall_s": self.stall_seconds})
                self.stalled.set()
                self.lost.set()
                return
            try:
                extra = {} if self.phase is None else {"phase": self.phase()}
                ok = self.store.heartbeat(self.lease, self.lease_seconds, photons=self.photons(), **extra)
            except DBAPIError as exc:  # transient DB trouble: try again next period
                log.warning("heartbeat failed", extra={"task": self.lease.task_id, "error": str(exc)})
                continue
            if not ok:
                self.lost.set()
                return

    def poke(self) -> None:
        """Send a heartbeat now (with the current photons and phase), not at the next period."""
        self._wake.set()

    def stop(self) -> None:
        self._stop_event.set()
        self._wake.set()
        self.join()


def compile_phase(kernel: str, eta: float) -> str:
    """What a shard reports while kernel ``kernel`` compiles for a medium of index ``eta``."""
    what = "the walk" if kernel == "walk_step" else f"the walk's {kernel} kernel"
    return f"compiling {what} for eta = {eta:g} (first run on this machine, ~1-2 min)"


class Worker:
    """One worker process: claims tasks from a ``JobStore`` and writes datasets to a storage."""

    def __init__(
        self, store: JobStore, storage: DatasetStorage, *, worker_id: str | None = None, lease_seconds: float = 60.0,
        heartbeat_seconds: float | None = None, once: bool = False, max_tasks: int | None = None,
        poll_seconds: float = 1.0, max_poll_seconds: float | None = None, stall_seconds: float | None = 300.0,
        keep_shard_files: bool = False, commit_retry_seconds: float = 120.0,
    ) -> None:
        self.store, self.storage = store, storage
        self.keep_shard_files = keep_shard_files
        self.worker_id = worker_id or f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:6]}"
        self.lease_seconds = lease_seconds
        self.heartbeat_seconds = heartbeat_seconds or lease_seconds / 4
        self.once, self.max_tasks, self.poll_seconds = once, max_tasks, poll_seconds
        # An idle worker's wait doubles from poll_seconds up to this: an idle fleet of 1,000
        # polls ~125 times a second at the 8 s default, not 1,000 (deploy/README.md, capacity).
        self.max_poll_seconds = IDLE_BACKOFF_CAP * poll_seconds if max_poll_seconds is None else max_poll_seconds
        if not poll_seconds > 0:
            raise ValueError(f"poll_seconds must be > 0; received {poll_seconds}")
        if not self.max_poll_seconds >= poll_seconds:
            raise ValueError(f"max_poll_seconds must be >= poll_seconds ({poll_seconds}); received {max_poll_seconds}")
        self.stall_seconds = stall_seconds
        self.commit_retry_seconds = commit_retry_seconds
        self.stopping = threading.Event()
        self.processed = 0
        self._specs: dict[str, SimulationSpec] = {}

    # --- run / loop / claim / process ---
    def run(self) -> int:
        """Install SIGTERM/SIGINT handlers and loop until done or stopped; the exit status."""
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, self._on_signal)
        log.info("worker started", extra={"worker": self.worker_id, "lease_s": self.lease_seconds})
        self.loop()
        log.info("worker stopped", extra={"worker": self.worker_id, "tasks": self.processed})
        return 0

    def _on_signal(self, signum, _frame) -> None:
        log.info("stop requested", extra={"worker": self.worker_id, "signal": signal.Signals(signum).name})
        self.stopping.set()

    def loop(self) -> int:
        """Claim and process until stopped, ``max_tasks`` reached, or (``once``) the queue is empty."""
        db_errors = idle = 0
        while not self.stopping.is_set():
            if self.max_tasks is not None and self.processed >= self.max_tasks:
                break
            try:
                lease = self.claim()
                db_errors = 0
            except DBAPIError as exc:
                db_errors += 1
                if db_errors >= 10:
                    raise
                log.warning("claim failed; retrying", extra={"error": str(exc), "failures": db_errors})
                self.stopping.wait(min(30.0, self.poll_seconds * 2**db_errors))
                continue
            if lease is None:
                # --once: leave only when no live job has a task that can still become claimable
                # (a merge waiting for running shards, a retry backing off, a lease to expire).
                if self.once and not self.store.has_pending_tasks():
                    break
                self.stopping.wait(self.idle_wait(idle))
                idle += 1
                continue
            idle = 0
            self.process(lease)
            self.processed += 1
        return self.processed

    def idle_wait(self, empty_claims: int) -> float:
        """Seconds to wait after ``empty_claims + 1`` empty claims in a row: ``poll_seconds``
        doubled per empty claim up to ``max_poll_seconds``, times a random 0.5-1.5 (jitter: a
        fleet started together does not poll in lock step). A claimed task resets the count."""
        base = min(self.max_poll_seconds, self.poll_seconds * 2.0 ** min(empty_claims, 30))
        return base * random.uniform(0.5, 1.5)

    def claim(self) -> Lease | None:
        """One lease or None."""
        return self.store.claim(self.worker_id, self.lease_seconds)

    def process(self, lease: Lease) -> None:
        """Run one leased task; every outcome is logged, none raises (except KeyboardInterrupt)."""
        fields = {"task": lease.task_id, "job": lease.job_id, "kind": str(lease.kind),
                  "shard": lease.shard_index, "attempt": lease.attempts, "token": lease.token}
        log.info("task claimed", extra=fields)
        photons = [0]
        last_progress: list[float | None] = [None]  # the stall clock starts at the first report (after compiling)
        phase: list[str | None] = [None]  # "compiling ..." while a kernel compiles (reported by heartbeats)
        beat = _Heartbeat(self.store, lease, self.lease_seconds, self.heartbeat_seconds, lambda: photons[0],
                          lambda: last_progress[0], self.stall_seconds if lease.kind == TaskKind.SHARD else None,
                          phase=lambda: phase[0])
        beat.start()
        try:
            if lease.kind == TaskKind.SHARD:
                self._process_shard(lease, beat, photons, last_progress, fields, phase)
            else:
                self._process_merge(lease, beat, fields)
        except (LeaseLost, JobNotFound) as exc:  # JobNotFound: the job was deleted meanwhile
            log.warning("result refused: lease lost", extra={**fields, "error": str(exc)})
        except _Abandon as exc:
            if beat.lost.is_set():
                log.warning("shard abandoned: lease lost", extra=fields)
            else:
                try:
                    released = self.store.release(lease)
                except DBAPIError as db_exc:
                    released = f"no (database error: {db_exc}); the lease will expire"
                log.info("shard abandoned: stopping; lease released", extra={**fields, "released": released, "reason": str(exc)})
        except _CommitUnknown as exc:
            log.error("shard not committed: database unreachable; the lease will expire and the shard be claimed "
                      "again unless a commit went through", extra={**fields, "error": str(exc)[:500]})
        except Exception as exc:  # the task failed: record it (retry or fail the job)
            error = f"{type(exc).__name__}: {exc}"
            try:
                # A non-finite table is deterministic (the same shards merge to the same numbers):
                # the job fails at once, naming the medium and the column, instead of retrying.
                retried = self.store.fail_task(lease, error, final=isinstance(exc, NonFiniteResult))
                log.error("task failed", extra={**fields, "error": error, "will_retry": retried})
            except (LeaseLost, JobNotFound):
                log.warning("task failed after its lease was lost", extra={**fields, "error": error})
            except DBAPIError as db_exc:  # the database is unreachable: the lease expiring retries the task
                log.error("task failed; the failure could not be recorded, the lease will expire and the task "
                          "be claimed again", extra={**fields, "error": error, "db_error": str(db_exc)[:300]})
        finally:
            beat.stop()

    def _spec(self, lease: Lease) -> SimulationSpec:
        if lease.job_id not in self._specs:
            self._specs[lease.job_id] = parse_spec(json.loads(lease.spec_json))
        return self._specs[lease.job_id]

    def _eta(self, lease: Lease) -> float:
        """The relative index of the leased shard's medium."""
        spec = self._spec(lease)
        return spec.media()[spec.task_of(lease.shard_index)[0]].eta

    def _process_shard(self, lease: Lease, beat: _Heartbeat, photons: list[int], last_progress: list,
                       fields: dict, phase: list | None = None) -> None:
        """Run task ``lease.shard_index`` (shard s of medium m, schema.media), write its tally as
        a file in the job's staging area, and commit the file's URI, size and sha256.

        While a kernel compiles (:func:`workers.walk.kernels.observe_compiles`) the heartbeat reports
        the phase at once (:func:`compile_phase`) and the stall clock is held: a compile is not
        a hung walk."""
        phase = [None] if phase is None else phase

        def progress(n: int) -> None:
            photons[0] += int(n)
            last_progress[0] = time.monotonic()
            if beat.lost.is_set():
                raise _Abandon("lease lost")
            if self.stopping.is_set():
                raise _Abandon("stopping")

        held = [False]  # the stall clock was running when the compile began

        def compiling(kernel: str, started: bool) -> None:
            phase[0] = compile_phase(kernel, self._eta(lease)) if started else None
            if started:
                held[0], last_progress[0] = last_progress[0] is not None, None  # held while it compiles
            elif held[0]:
                last_progress[0] = time.monotonic()  # the compile's minutes are not a stall
            log.info("kernel compiling" if started else "kernel compiled", extra={**fields, "kernel": kernel})
            beat.poke()

        progress.compiling = compiling  # read by _walk (a fake walk may ignore it)

        payload, n_photons, elapsed_s = self._walk(lease, progress)
        if beat.lost.is_set():
            raise _Abandon("lease lost")
        files = JobFiles(self.storage, lease.job_id)
        # One file per attempt (named by the lease token): a stale worker never overwrites the
        # file a commit recorded.
        ref = files.write(f"shards/{lease.shard_index:08d}-{lease.token}.tally", payload)
        try:
            self._commit_shard(lease, ref, n_photons, elapsed_s, fields)
        except _CommitUnknown:
            raise  # the file stays: a commit whose answer was lost may have recorded it
        except BaseException:
            files.delete(ref)  # not recorded: nobody will read it
            raise
        log.info("shard done", extra={**fields, "photons": n_photons, "elapsed_s": round(elapsed_s, 3),
                                      "payload_bytes": ref.bytes})

    def _commit_shard(self, lease: Lease, ref, photons: int, elapsed_s: float, fields: dict) -> None:
        """``complete_shard``, retried through database errors (a restart, a failover, a dropped
        link) for up to ``commit_retry_seconds``: a finished walk is not thrown away for a blip.

        A failed attempt may have committed with only its answer lost; before trying again the
        task's recorded result is read back, and our file (its name carries the lease token)
        there means done. The fence refuses the retry if the lease went to another worker
        meanwhile (LeaseLost). Raises :class:`_CommitUnknown` when giving up after an error.
        """
        deadline = time.monotonic() + self.commit_retry_seconds
        delay, failures = 0.2, 0
        while True:
            try:
                if failures:
                    recorded = self.store.shard_result(lease.job_id, lease.shard_index)
                    if getattr(recorded, "uri", None) == ref.uri:
                        log.info("commit found recorded after a lost answer", extra=fields)
                        return
                self.store.complete_shard(lease, ref, photons=photons, elapsed_s=elapsed_s)
                return
            except DBAPIError as exc:
                failures += 1
                if time.monotonic() + delay > deadline or self.stopping.is_set():
                    raise _CommitUnknown(f"the shard's commit failed {failures} times: {exc}") from exc
                log.warning("commit failed; retrying", extra={**fields, "error": str(exc)[:300], "failures": failures})
                self.stopping.wait(delay)
                delay = min(5.0, 2 * delay)

    def _walk(self, lease: Lease, progress) -> tuple[bytes, int, float]:
        """Walk the leased shard: its tally's bytes, its photons and the walk's seconds
        (``bench.fleet`` puts an instant fake here to load the queue alone)."""
        with observe_compiles(getattr(progress, "compiling", lambda _kernel, _started: None)):
            tally = run_task(self._spec(lease), lease.shard_index, progress=progress)
        return tally.to_bytes(), tally.photons, tally.elapsed_s

    def _process_merge(self, lease: Lease, beat: _Heartbeat, fields: dict) -> None:
        t0 = time.perf_counter()
        version = run_merge_task(self.store, self.storage, lease, keep_files=self.keep_shard_files)
        elapsed = round(time.perf_counter() - t0, 3)
        if version is None:
            log.info("fold advanced", extra={**fields, "elapsed_s": elapsed})
            return
        spec = self._spec(lease)
        log.info("dataset published", extra={**fields, "dataset": spec.name, "version": version, "elapsed_s": elapsed})


if __name__ == "__main__":
    from service.worker_command import run_as_script

    sys.exit(run_as_script())
