"""Run one shard of a simulation: a pure function of (spec, shard index).

The shard's photons [start, stop) of every configuration (incidence angle x channel) are
launched in a fixed order, photon-major: (p, c) for p in range(start, stop) for c in configs.
Finished lanes are harvested after every call of the step function and refilled in lane order,
so the schedule, and with it every float64 sum, is fixed by the spec alone.  What is fixed
before the run starts is its plan (:mod:`workers.run.plan`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, fields
from typing import Callable

import numpy as np
import torch

from schema import SimulationSpec

from workers.walk.binning import histogram_index
from workers.walk.connections import Vertices, VertexBuffer, connection_function
from workers.walk.engine import init_engine
from workers.walk.harvest import harvest_fields, harvest_function
from workers.walk.hybrid import ENTRY_OUTPUTS, harvest_entries_function
from workers.walk.path_roulette import check_steps_per_call
from workers.fold.reweight import MemberTallies, member_prefix
from .plan import HARVEST_DIVISOR, LANE_MULTIPLE, TAIL_FILL, VERTEX_CHUNK, ShardPlan
from workers.fold.tally import BATCH_ESTIMATORS, BatchAccumulator, PhotonAccumulator, ShardTally, entry_square_keys
from workers.walk.walk import EMPTY, EXITED, RUNNING, TRUNCATED, Lanes, step_function

__all__ = ["ordered_sum", "run_shard"]


def ordered_sum(values: np.ndarray) -> float:
    """:func:`workers.fold.tally.ordered_sum` with the same bits, ~6x faster: torch's cumulative
    sum of float64 on the CPU is one loop that carries the running sum in a register, (((0 + v_0)
    + v_1) + ...), where numpy's stores and reloads it (0.6 against 3.3 ns a value, and 4 in a
    bincount; tests/workers/test_tally.py checks the bits)."""
    return torch.cumsum(torch.from_numpy(values), 0)[-1].item() + 0.0 if values.size else 0.0


def _tail_length(running: int, multiple: int = LANE_MULTIPLE) -> int:
    """Lanes a tail of `running` photons is stepped in: the next multiple of the vector width
    (no lane in the kernel's scalar remainder), at least one."""
    return max(multiple, -(-running // multiple) * multiple)


@dataclass(frozen=True)
class _Kernels:
    """The (compiled or eager) functions a shard run calls, chosen once from its plan."""

    step: Callable  # steps a chunk of lanes in place (workers.walk.walk.step_function)
    # records lanes not running and refills them (workers.walk.harvest.harvest_block): harvest_fields(exits, members);
    # the hybrid's returns its entries per photon first (workers.walk.hybrid.harvest_with_entries)
    harvest: Callable
    connect: Callable  # both connection techniques for a chunk of vertices

    @classmethod
    def for_plan(cls, plan: ShardPlan, members: bool, wrap: Callable[[str, Callable], Callable] | None = None) -> "_Kernels":
        """The plan's kernels (members: the walk has reweighted members); wrap(name, kernel), if
        given, replaces each (a profiler's timer)."""
        c = plan.compiled
        harvest = harvest_entries_function(c, members) if "hybrid" in plan.estimators else harvest_function(c, "exits" in plan.estimators, members)
        kernels = cls(step=step_function(plan.params, plan.n_steps, plan.connect, c), harvest=harvest, connect=connection_function(c))
        if wrap is None:
            return kernels
        return cls(**{f.name: wrap(f.name, getattr(kernels, f.name)) for f in fields(cls)})


@dataclass
class _Counters:
    """Work done, for the shard's info: steps = calls x steps per call; photon_steps = interaction
    steps (free paths) of finished photons; vertices = connected scattering vertices."""

    steps: int = 0
    photon_steps: int = 0
    vertices: int = 0


class _Runner:
    """The mutable bookkeeping of one shard run (kept out of the pure entry point): the lanes and
    the chunks they are stepped in, the accumulators, the vertices waiting for connection."""

    def __init__(self, plan: ShardPlan, progress: Callable[[int], None] | None, members: tuple[float, ...] = (),
                 wrap_kernels: Callable[[str, Callable], Callable] | None = None):
        self.plan, self.progress = plan, progress
        self.kernels = _Kernels.for_plan(plan, bool(members), wrap_kernels)
        self.harvest_fields = harvest_fields("exits" in plan.estimators, bool(members))
        # The hybrid's harvest also makes its entries (workers.walk.hybrid.harvest_with_entries).
        self.entry_args = (plan.first_vertex, plan.entry_layout) if "hybrid" in plan.estimators else ()
        self.count = _Counters()
        batch_estimators = [e for e in plan.estimators if e in BATCH_ESTIMATORS]
        photon_estimators = [e for e in plan.estimators if e not in BATCH_ESTIMATORS]
        ranges = plan.spec.batch_photon_ranges(plan.shard_index)
        self.acc = BatchAccumulator(batch_estimators, plan.cfgs.n, plan.layout.shape, ranges)
        self.photons = PhotonAccumulator(photon_estimators, plan.cfgs.n, plan.layout.shape, ordered_sum=ordered_sum)
        self.members = None  # a shared walk's other albedos (workers.fold.reweight)
        if members:
            walked = set(plan.cfgs.albedo.tolist())
            if len(walked) != 1 or batch_estimators:
                raise ValueError("a shared walk needs one albedo for every configuration and only per-photon estimators (exits, hybrid)")
            self.members = MemberTallies(members, walked.pop(), plan.table.w0.double().numpy(), photon_estimators,
                                         plan.cfgs.n, plan.layout.shape)  # fmt: skip
        self.vertex_buffer = VertexBuffer(VERTEX_CHUNK)
        # Lanes: [0, stepped) hold every running photon; chunks are views stepped one by one.
        self.lanes = Lanes.empty(plan.n_lanes + 1)  # the last: a scratch lane that pads harvest blocks, never stepped
        self.stepped = 0  # lanes [0, stepped) are stepped, in chunks of at most plan.chunk (set_stepped)
        self.chunks: list[Lanes] = []
        self.offsets: list[int] = []  # each chunk's first lane
        self.set_stepped(plan.n_lanes)
        self.next_launch = 0
        self.launch = torch.tensor([plan.start, 0, plan.n_launch, plan.cfgs.n], dtype=torch.int64)  # the harvest's launch numbers
        self.n_valid = torch.zeros((), dtype=torch.int64)  # the real lanes of a harvest call
        self.tail_lanes = None  # photons still running at the tail's first compaction
        self.tail_chunks: list[int] = []  # the lanes stepped after each compaction of the tail, in order

    # -- lanes --------------------------------------------------------------------------------
    def finish_and_refill(self, idx: torch.Tensor, finished: bool = True) -> tuple[int, int]:
        """Record the finished photons of lanes idx (ascending lanes not running) and launch the
        next photons into those lanes, in lane order: one call of
        :func:`workers.walk.harvest.harvest_block` over them all (at most every lane), so the work
        is per lane harvested, not per lane of the array.  The exit tally's entries come from the
        same pass, and so do the hybrid's, which are tallied if `finished` (every lane of idx holds
        a finished photon: harvest()) and not at the first fill (every lane EMPTY).

        The call's length is padded to a multiple of LANE_MULTIPLE with the scratch lane (also
        on the eager path: one code path, whose bits the tests compare across paddings).  Its
        records are tallied as the kernel returns them, without copies: per-lane records cut
        to the real lanes (views), the hybrid's entries whole, their padding set to weight 0
        (tally_entries).  Returns (photons finished, photons launched)."""
        plan, L = self.plan, self.lanes
        launched = min(len(idx), plan.n_launch - self.next_launch)
        self.next_launch += launched
        m = len(idx)
        if m == 0:
            return 0, launched
        names = self.harvest_fields
        pad = -m % LANE_MULTIPLE
        if pad:  # the kernel takes any multiple of the vector width: pad with the scratch lane
            idx = torch.cat((idx, torch.full((pad,), plan.n_lanes, dtype=torch.int64)))
        self.launch[1] = self.next_launch - launched  # written in place: building small tensors per call cost ~1 % of a short walk
        self.n_valid.fill_(m)
        out = self.kernels.harvest(idx, self.n_valid, L, plan.table, self.launch, plan.exit_bins, *self.entry_args)
        if self.entry_args:
            entries, out = out[:ENTRY_OUTPUTS], out[ENTRY_OUTPUTS:]
            if finished:
                self.tally_entries(entries, out[names.index("nscat")] if self.members is not None else None, m)
        rec = {name: v[:m].numpy() for name, v in zip(names, out) if name != "steps"}
        self.count.photon_steps += int(out[names.index("steps")])
        # Lanes that hold no finished photon (or no exit) have records of weight 0 (the spare key,
        # whose configuration is 0; flat spread over bins): added to a sum they leave it as it is, bit for bit,
        # and they are no events (those count nonzero weights), so the tallies take every record
        # without selecting them first; the members select, to reweight.
        key = rec["key"]
        # One configuration (every bench medium, every walk of a sweep's group): all 0, without
        # dividing int64 record by record (~4 ns a photon of M2's exit walk).
        cfg = key % plan.cfgs.n if plan.cfgs.n > 1 else np.zeros_like(key)
        self.photons.add_walk(cfg, rec["absorbed"], rec["truncated"])
        if "exits" in plan.estimators:
            self.photons.add_exits("exits", rec["flat"], rec["g"], rec["s"])
        if self.members is not None:
            done = key < len(self.acc.sizes) * plan.cfgs.n
            st = rec["status"]
            if "exits" in plan.estimators:
                ex = st == EXITED
                self.members.add_exits(rec["flat"][ex], rec["g"][ex], rec["s"][ex], rec["nscat"][ex])
            self.members.add_walk(cfg[done], st[done] == EXITED, st[done] == TRUNCATED, rec["w"][done], rec["nscat"][done])
        return self.acc.finish_photons(key), launched

    def fill(self) -> int:
        """Launch the first photons into every lane (all EMPTY); returns how many were launched."""
        return self.finish_and_refill(torch.arange(self.plan.n_lanes), finished=False)[1]

    def set_stepped(self, n: int) -> None:
        """Step lanes [0, n) from now on (n a multiple of LANE_MULTIPLE): chunks of plan.chunk
        lanes, the last one shorter (one compiled kernel serves every length:
        workers.walk.kernels.compile_kernel's any_length)."""
        self.stepped = n
        self.offsets = list(range(0, n, self.plan.chunk))
        self.chunks = [self.lanes.view(a, min(a + self.plan.chunk, n)) for a in self.offsets]

    def shrinkable(self, running: int) -> bool:
        """Whether compact() would run now: nothing is left to launch and no more than TAIL_FILL
        of the stepped lanes hold a running photon."""
        if self.next_launch < self.plan.n_launch:
            return False
        return running <= TAIL_FILL * self.stepped and _tail_length(running) < self.stepped

    def compact(self, running: int) -> None:
        """Tail of the shard (nothing left to launch): once the running photons fill no more than
        TAIL_FILL of the stepped lanes, move them, in lane order, to the front and step only
        those lanes (rounded up to LANE_MULTIPLE).  A step costs the same for idle lanes, and
        the tail is long where paths are: an albedo-1 walk's lanes drained for thousands of steps
        at ~45 % occupancy in fixed chunks (BENCHMARKS.md).  Moving a photon changes nothing of
        its path (its stream is its own), only where in the order of a harvest's records it is."""
        if not self.shrinkable(running):
            return
        n = self.stepped
        idx = torch.nonzero(self.lanes.status[:n] == RUNNING).squeeze(1)
        for t in self.lanes.tensors():
            t[: len(idx)] = t[idx]
        self.lanes.status[len(idx) : n] = EMPTY
        if self.tail_lanes is None:
            self.tail_lanes = len(idx)
        self.tail_chunks.append(_tail_length(len(idx)))  # every lane moved is stepped, whatever the caller counted
        self.set_stepped(self.tail_chunks[-1])

    def harvest(self, running: int) -> int:
        """Tally the lanes that finished, refill them; returns the lanes running afterwards."""
        st = self.lanes.status[: self.stepped].numpy()  # numpy's flatnonzero: ~2.5x faster than torch.nonzero here
        launching = self.next_launch < self.plan.n_launch
        # While photons are left to launch every lane not running is refilled; afterwards only the
        # finished ones are recorded.  Either way every lane harvested here holds a finished
        # photon: lanes become EMPTY only once nothing is left to launch (the refill's launches
        # run out, or a fill with fewer photons than lanes), so while launching there are none
        # but at the first fill, which fill() harvests (the hybrid's entries rely on it).
        free = st != RUNNING if launching else (st != RUNNING) & (st != EMPTY)
        finished, launched = self.finish_and_refill(torch.from_numpy(np.flatnonzero(free)))
        if self.acc.ready:
            self.flush_vertices(force=True)  # a batch folds only after all its vertices are tallied
            self.acc.fold_ready()
        if self.progress is not None:
            self.progress(finished)
        running += launched
        self.compact(running)
        return running

    # -- exit estimator and hybrid ------------------------------------------------------------
    def tally_entries(self, entries, nscat: torch.Tensor | None, m: int) -> None:
        """Tally the hybrid estimator's entries of one harvest (the first-vertex connection
        samples, single, and the exit after two or more scatterings, multiple;
        workers.walk.hybrid.photon_entries), the first m positions real, the rest padding.  A
        harvest is the unit in which the tallies add (one bincount per quantity over its entries
        in memory order), which fixes the association of their float sums: the harvests are fixed
        by the spec, so are the bits.  The padding's entries are set to weight 0 at in-range keys
        in place (the kernel's fresh outputs): they leave every sum as it is and are no events,
        and the arrays stay whole, which the bincounts read without a copy (cutting them to m
        rows copied every entry-major array: BENCHMARKS.md).  nscat: the photons' scattering
        counts, by which the members reweight (they take the m real photons: their group sums are
        pairwise, whose association more terms would change, and they copy their inputs anyway)."""
        flat2, g, s, key, weight = (v.numpy() for v in entries)
        if nscat is not None:
            f = flat2[:m]
            self.members.add_hybrid(f, g[:m], s[:m], entry_square_keys(f, self.photons.layout), nscat[:m].numpy())
        if m < len(flat2):
            g[m:], s[m:], weight[:, m:] = 0.0, 0.0, 0.0
            flat2[m:], key[:, m:] = flat2[:1], key[:, :1]  # the first photon's keys: in range
        self.photons.add_photons("hybrid", flat2, g, s, key, weight)

    def flat_index(self, cfg, comp, spatial, direction) -> torch.Tensor:
        """Index into the flattened [cfg, comp, n_r + 1, n_theta, n_cos, n_phi] histogram."""
        layout = self.plan.layout
        return histogram_index(cfg, comp, spatial, direction, (layout.n_r + 1) * layout.n_theta, layout.n_cos * layout.n_phi)

    # -- connection estimator -----------------------------------------------------------------
    def collect_vertices(self, vertex, offset: int) -> None:
        """Keep the vertices of the last step of the chunk at lane `offset` (`vertex` as the step
        function returns it); connect them once a chunk of VERTEX_CHUNK is full."""
        collided, ux_in, uy_in, uz_in, w_in = vertex
        local = torch.nonzero(collided).squeeze(1)
        idx = local + offset
        if len(idx) == 0:
            return
        L = self.lanes
        v = Vertices(
            x=L.x[idx], y=L.y[idx], z=L.z[idx], ux=ux_in[local], uy=uy_in[local], uz=uz_in[local], vx=L.ux[idx], vy=L.uy[idx],
            vz=L.uz[idx], w=w_in[local], cfg=L.cfg[idx], photon=L.photon[idx], draw=L.step[idx] - 1,
            multiple=(L.nscat[idx] >= 2).to(torch.int64),
        )  # fmt: skip
        self.count.vertices += len(idx)
        if self.vertex_buffer.add(v):
            self.flush_vertices(force=False)

    def flush_vertices(self, force: bool) -> None:
        """Connect the full chunks of vertices waiting, and with force the short last one too."""
        for v in self.vertex_buffer.chunks(force):
            self.connect_chunk(v)

    def connect_chunk(self, v: Vertices) -> None:
        """Tally both connection techniques for up to VERTEX_CHUNK vertices.

        A short chunk is padded to VERTEX_CHUNK (the compiled kernel has one static shape) with
        copies of its first vertex, whose results are cut off before tallying.
        """
        n = len(v)
        (Gu, Su, spu, dru), (Gp, Sp, spp, drp) = self.kernels.connect(v.pad(VERTEX_CHUNK), self.plan.table, self.plan.geo)
        cfg, comp = v.cfg, v.multiple
        batch = self.acc.batch_of(v.photon.numpy())
        flat = self.flat_index(cfg[:, None], comp[:, None], spu[:n], dru[:n])
        nb = flat.shape[1]
        self.acc.add_hist("connections", np.repeat(batch, nb), flat.reshape(-1).numpy(),
                          Gu[:n].reshape(-1).double().numpy(), Su[:n].reshape(-1).double().numpy())  # fmt: skip
        flat = self.flat_index(cfg, comp, spp[:n], drp[:n])
        self.acc.add_hist("connections", batch, flat.numpy(), Gp[:n].double().numpy(), Sp[:n].double().numpy())

    # -- main loop ------------------------------------------------------------------------------
    def run(self) -> ShardTally:
        t0, c0 = time.perf_counter(), time.thread_time()
        with torch.no_grad():  # also around the first refill: grad mode is part of a compiled graph's key
            tally = self._run(t0)
        tally.info["cpu_s"] = time.thread_time() - c0  # this thread's CPU (torch runs one intra-op thread per shard)
        if self.members is not None:
            tally.info["members"] = len(self.members)
        return tally

    def _run(self, t0: float) -> ShardTally:
        plan = self.plan
        running = self.fill()
        # Harvesting costs a pass over the lanes plus Python work: wait until an eighth of the
        # lanes has finished (or none runs) so the cost is spread over many photons.
        harvest_at = max(1, plan.n_lanes // HARVEST_DIVISOR)
        if plan.params.roulette is not None:  # workers.walk.path_roulette: played by the step function after its last step
            check_steps_per_call(plan.params.roulette[0], plan.n_steps)
        while running > 0:
            running = finished = 0
            for chunk, offset in zip(self.chunks, self.offsets):
                counts, vertex = self.kernels.step(chunk)
                now_running, now_finished = counts.tolist()  # one conversion: a tail runs ~10^4 calls
                running, finished = running + now_running, finished + now_finished
                if plan.connect:
                    self.collect_vertices(vertex, offset)
            self.count.steps += plan.n_steps
            if finished >= harvest_at or (running == 0 and finished > 0) or (finished and self.shrinkable(running)):
                running = self.harvest(running)
        self.flush_vertices(force=True)
        self.acc.fold_ready()
        assert self.acc.complete, "every batch must have folded once all photons finished"
        stats, counts = self.photons.finish(plan.stop - plan.start)
        batch_stats, batch_counts = self.acc.finish()
        for j, (m_stats, m_counts) in enumerate(self.members.finish(plan.stop - plan.start) if self.members is not None else []):
            stats.update({member_prefix(j) + k: v for k, v in m_stats.items()})
            counts.update({member_prefix(j) + k: v for k, v in m_counts.items()})
        info = {
            "photons": plan.n_launch, "lanes": plan.n_lanes, "lane_steps": self.count.steps, "photon_steps": self.count.photon_steps,
            "vertices": self.count.vertices, "tail_lanes": self.tail_lanes, "tail_chunks": self.tail_chunks, "elapsed_s": time.perf_counter() - t0,
            "engine": "compiled" if plan.compiled else "eager", "torch": torch.__version__,
        }  # fmt: skip
        return ShardTally(plan.shard_index, {**stats, **batch_stats}, {**counts, **batch_counts}, plan.stop - plan.start, info)


def run_shard(spec: SimulationSpec, shard_index: int, *, progress: Callable[[int], None] | None = None,
              members: tuple[float, ...] = (), wrap_kernels: Callable[[str, Callable], Callable] | None = None) -> ShardTally:
    """Simulate shard `shard_index` of `spec`; a pure function of its inputs.

    members: further albedos (each <= the spec's, one-channel medium, exits or hybrid) tallied
    from the same walk by reweighting (:mod:`workers.fold.reweight`); member j's quantities carry
    the prefix ``member_prefix(j)`` in the tally, the spec's own are unchanged.

    progress, if given, is called with the number of photons (all configurations) finished since
    the last call.  The statistics in the result do not depend on the machine, the thread count
    or when the shard runs; `info` carries timings and counters that do.

    wrap_kernels(name, kernel), if given, returns what the run calls instead of each kernel
    ("step", "harvest", "connect"): a profiler's timers (workers.measure.profile).
    """
    init_engine()
    return _Runner(ShardPlan.build(spec, shard_index), progress, tuple(members), wrap_kernels).run()
