"""Progress tells the truth while a kernel compiles: the worker reports the phase in a heartbeat
sent at once (not at the next period), the progress read shows it (SQLite and PostgreSQL), the
stall clock is held through a compile, the CLI line says "compiling ..." instead of "0 photons/s",
and :func:`workers.walk.kernels.observe_compiles` reports a real compile (and not a load)."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import pytest

from schema import parse_spec
from service.datasets import DatasetStorage
from service.runner import format_progress
from service.worker import Worker, compile_phase
from tests.api.conftest import TINY_SPEC


def _wait_for(predicate, timeout=10.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    return predicate()


class CompilingWorker(Worker):
    """A walk that 'compiles' (tells the observer) until the test lets it go, then walks."""

    seen: list = []

    def _walk(self, lease, progress):
        progress.compiling("walk_step", True)
        self.seen.append(_wait_for(lambda: self.store.progress(lease.job_id).phase))
        self.seen.append(self.store.progress(lease.job_id))
        progress.compiling("walk_step", False)
        self.seen.append(_wait_for(lambda: self.store.progress(lease.job_id).phase is None))
        progress(40)
        return b"tally", 40, 0.1


def test_a_compiling_shard_reports_its_phase_at_once(store, tmp_path):
    spec = parse_spec(dict(TINY_SPEC, shards=1, batches_per_shard=2, medium=dict(TINY_SPEC["medium"], eta=1.4)))
    job = store.submit(spec)
    worker = CompilingWorker(store, DatasetStorage(str(tmp_path / "data")), heartbeat_seconds=30)  # no periodic beat
    CompilingWorker.seen = []
    t0 = time.monotonic()
    worker.process(store.claim("w", 60))
    phase, during, cleared = CompilingWorker.seen
    assert phase == "compiling the walk for eta = 1.4 (first run on this machine, ~1-2 min)"
    assert during.shards_compiling == 1 and during.shards_running == 1 and during.photons_done == 0
    assert cleared is True and time.monotonic() - t0 < 20  # both heartbeats sent when poked, not after 30 s
    done = store.progress(job.id)
    assert done.phase is None and done.shards_compiling == 0 and done.shards_done == 1


def test_the_stall_clock_is_held_while_a_kernel_compiles(store, tmp_path):
    """A kernel compiling after the walk reported progress (a second kernel of the shard) for
    longer than stall_seconds does not cost the lease."""
    spec = parse_spec(dict(TINY_SPEC, shards=1, batches_per_shard=2))
    store.submit(spec)

    class LateCompile(Worker):
        def _walk(self, lease, progress):
            progress(10)
            progress.compiling("exit_bins", True)
            time.sleep(1.0)  # five stall periods
            progress.compiling("exit_bins", False)
            progress(10)
            return b"tally", 20, 0.1

    worker = LateCompile(store, DatasetStorage(str(tmp_path / "data")), heartbeat_seconds=0.05, stall_seconds=0.2)
    lease = store.claim("w", 60)
    worker.process(lease)
    assert store.progress(lease.job_id).shards_done == 1  # committed: the lease was never lost


def test_compile_phase_names_the_kernel_and_eta():
    assert compile_phase("walk_step", 1.3) == "compiling the walk for eta = 1.3 (first run on this machine, ~1-2 min)"
    assert "exit_bins kernel for eta = 1" in compile_phase("exit_bins", 1.0)


def _progress(**kw):
    base = dict(state="running", shards_done=0, shards_total=8, shards_running=2, photons_done=0,
                rate_photons_per_s=None, eta_s=None, merge_state="waiting", phase=None, shards_compiling=0)
    return SimpleNamespace(**(base | kw))


def test_the_cli_line_says_compiling_until_photons_arrive():
    phase = compile_phase("walk_step", 1.3)
    line = format_progress(_progress(phase=phase, shards_compiling=2))
    assert line.endswith(phase) and "photons" not in line and "-/s" not in line
    line = format_progress(_progress(phase=phase, shards_compiling=1, photons_done=5000, rate_photons_per_s=1e3,
                                     eta_s=10))
    assert "photons 5.00k  1.00k/s  ETA -" in line and line.endswith(f"(1 compiling: {phase})")  # the rate counts the compile
    assert "compiling" not in format_progress(_progress(photons_done=10)) and "ETA 10s" in format_progress(
        _progress(photons_done=10, eta_s=10))


@pytest.mark.slow  # one real torch.compile of a two-operation kernel (~20 s on two busy cores)
def test_observe_compiles_reports_a_compile_and_not_a_load(tmp_path, monkeypatch):
    import torch

    from workers.walk import kernels

    monkeypatch.setenv("BSSRDF_KERNEL_CACHE", str(tmp_path / "kernels"))
    events, lock = [], threading.Lock()

    def twice(x):
        return x * 2.0 + 1.0

    def observer(name, started):
        with lock:
            events.append((name, started))

    x = torch.arange(4, dtype=torch.float64)
    with kernels.observe_compiles(observer):
        out = kernels.compile_kernel(twice, "phase_test")(x)
        assert torch.equal(out, twice(x)) and events == [("phase_test", True), ("phase_test", False)]
        events.clear()
        again = kernels.compile_kernel(twice, "phase_test")(x)  # a new process's view: loaded from the artifact
        assert torch.equal(again, out) and events == []
    assert observer not in kernels._observers  # unregistered when the block ends
