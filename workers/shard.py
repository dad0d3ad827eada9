"""Run one shard of a simulation: a pure function of (spec, shard index).

The shard's photons [start, stop) of every configuration (incidence angle x channel) are
launched in a fixed order, photon-major: (p, c) for p in range(start, stop) for c in configs.
Finished lanes are harvested after every call of the step function and refilled in lane order,
so the schedule, and with it every float64 sum, is fixed by the spec alone.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from schema import SimulationSpec

from .binning import BinLayout
from .connections import ConnectionGeometry, connection_function
from .engine import init_engine
from .harvest import ExitBins, exit_function, finish_function
from .optics import fresnel_dielectric, incident_refracted_direction
from .rng import photon_words, stream_key, to_i32
from .tally import BatchAccumulator, ShardTally
from .walk import EMPTY, EXITED, RUNNING, ConfigTable, Lanes, WalkParams, compile_enabled, step_function

__all__ = ["run_shard", "Configs", "build_configs", "CHUNK", "VERTEX_CHUNK"]

CHUNK = 1 << 14  # lanes per call of the compiled step (one static shape for every shard); 2^15 ran M1 ~30 % slower on a 512 KiB-L2 machine
EAGER_CHUNK = 1 << 12  # lanes per call on the eager path, which has no per-call overhead to hide
CONNECT_CHUNK = 1 << 11  # lanes per call with connections: their kernel dominates, few photons run
MAX_CHUNKS = 4  # 2^16 lanes in all: enough photons in flight to keep every chunk full
TAIL_DIVISOR = 8  # exit walk: the last photons of a shard run in chunks of 1/TAIL_DIVISOR the lanes
PHOTONS_PER_LANE = 32  # launches per lane before using more chunks: keeps the tail short
VERTEX_CHUNK = 1 << 11  # vertices per connection kernel call
EXIT_STEPS_PER_CALL = 8  # steps per compiled call between harvests (exit estimator)
EXIT_BLOCK = 1 << 12  # exit events per call of the compiled exit lookup (a harvest of M2 has ~7500)
HARVEST_DIVISOR = 8  # harvest once 1/HARVEST_DIVISOR of the lanes has finished (4 and 32 ran M1 slower here)


@dataclass(frozen=True)
class Configs:
    """Per-configuration constants; configuration c = incidence index * n_channels + channel."""

    incidence_deg: list[float]
    channel_names: list[str]
    sigma_t: np.ndarray  # [n_cfg] 1/mm
    albedo: np.ndarray
    g: np.ndarray
    r_spec: np.ndarray  # specular reflectance at entry
    table: ConfigTable
    eta: float

    @property
    def n(self) -> int:
        return len(self.sigma_t)

    def channel_of(self, c: int) -> int:
        return c % len(self.channel_names)

    def incidence_of(self, c: int) -> float:
        return self.incidence_deg[c // len(self.channel_names)]


def build_configs(spec: SimulationSpec) -> Configs:
    channels = spec.channels()
    eta = float(spec.medium.eta)
    rows = []
    for i_inc, theta in enumerate(spec.incidence_deg):
        cos_i = math.cos(math.radians(theta))
        r_spec = float(fresnel_dielectric(torch.tensor(cos_i, dtype=torch.float64), eta))
        ux0, _, uz0 = incident_refracted_direction(math.radians(theta), eta)
        for i_ch, ch in enumerate(channels):
            fingerprint = json.dumps(
                [i_inc, theta, i_ch, ch.sigma_a, ch.sigma_s, ch.g, eta], separators=(",", ":")
            )
            k0, k1 = stream_key(spec.seed, fingerprint)
            rows.append((ch.sigma_t, ch.albedo, ch.g, r_spec, ux0, uz0, k0, k1))
    cols = list(zip(*rows))
    f32 = lambda v: torch.tensor(v, dtype=torch.float32)  # noqa: E731
    table = ConfigTable(
        albedo=f32(cols[1]), g=f32(cols[2]), w0=f32([1.0 - r for r in cols[3]]),
        ux0=f32(cols[4]), uz0=f32(cols[5]),
        k0=to_i32(torch.tensor(cols[6], dtype=torch.int64)), k1=to_i32(torch.tensor(cols[7], dtype=torch.int64)),
    )  # fmt: skip
    return Configs(
        incidence_deg=list(spec.incidence_deg), channel_names=[c.name for c in channels],
        sigma_t=np.array(cols[0]), albedo=np.array(cols[1]), g=np.array(cols[2]),
        r_spec=np.array(cols[3]), table=table, eta=eta,
    )  # fmt: skip


def bin_layout(spec: SimulationSpec) -> BinLayout:
    return BinLayout(spec.radial_edges_mm(), spec.theta_s_edges(), spec.cos_theta_o_edges(), spec.phi_o_edges())


def chunk_count(n_launch: int, chunk: int) -> int:
    """Chunks of `chunk` lanes for a shard: enough that each lane runs about PHOTONS_PER_LANE
    photons (fewer lanes keep the tail, where lanes fall idle, short), at most MAX_CHUNKS."""
    return int(min(MAX_CHUNKS, max(1, math.ceil(n_launch / (PHOTONS_PER_LANE * chunk)))))


class _Runner:
    """The mutable bookkeeping of one shard run (kept out of the pure entry point)."""

    def __init__(self, spec: SimulationSpec, shard_index: int, progress: Callable[[int], None] | None):
        self.spec = spec
        self.cfgs = build_configs(spec)
        self.layout = bin_layout(spec)
        self.start, self.stop = spec.shard_photon_range(shard_index)
        self.n_launch = (self.stop - self.start) * self.cfgs.n
        self.next_launch = 0
        self.progress = progress
        self.estimators = ["exits", "connections"] if spec.estimator == "both" else [spec.estimator]
        self.acc = BatchAccumulator(self.estimators, self.cfgs.n, self.layout.shape, spec.batch_photon_ranges(shard_index))
        self.compiled = compile_enabled()
        self.connect = "connections" in self.estimators
        self.chunk = CONNECT_CHUNK if self.connect else CHUNK if self.compiled else EAGER_CHUNK
        self.lanes = Lanes.empty(chunk_count(self.n_launch, self.chunk) * self.chunk)
        self.lanes_list = self.lanes.tensors()
        self.chunks = [[t[a : a + self.chunk] for t in self.lanes_list] for a in range(0, len(self.lanes.status), self.chunk)]
        self.active = len(self.chunks)  # chunks [0, active) hold every running lane
        # A step costs the same for idle lanes: a shard's last photons, the longest paths, are
        # stepped in one short chunk (compiled: a second shape) once they fit.  Not with
        # connections, whose chunks are short already and whose kernel dominates.
        self.tail_chunk = None if self.connect else self.chunk // TAIL_DIVISOR
        self.tail_lanes = None  # photons still running when the tail chunk took over
        self.table_tensors = self.cfgs.table.tensors()
        abs_g = np.abs(self.cfgs.table.g.numpy())
        self.params = WalkParams(
            inv_eta=1.0 / self.cfgs.eta, analog=spec.absorption == "analog", max_scatter=spec.max_scatter,
            hg_branch="large" if (abs_g >= 0.1).all() else "small" if (abs_g < 0.1).all() else "mixed",
        )  # fmt: skip
        n_steps = 1 if self.connect else EXIT_STEPS_PER_CALL
        self.step = step_function(self.params, n_steps, self.connect, self.compiled)
        self.finish_fn = finish_function(self.compiled)
        self.connect_fn = connection_function(self.compiled)
        self.sigma_t = torch.tensor(self.cfgs.sigma_t, dtype=torch.float64)
        radial_mm = torch.from_numpy(self.layout.radial_mm[[self.cfgs.channel_of(c) for c in range(self.cfgs.n)]])  # [cfg, n_r + 1]
        edges_opt = radial_mm * self.sigma_t[:, None]
        self.geo = ConnectionGeometry(
            r_lo=edges_opt[:, :-1].to(torch.float32).contiguous(), r_hi=edges_opt[:, 1:].to(torch.float32).contiguous(),
            n_theta=self.layout.n_theta, n_cos=self.layout.n_cos, n_phi=self.layout.n_phi, eta=self.cfgs.eta,
        )  # fmt: skip
        self.tally_exit_events = "exits" in self.estimators
        self.batch_starts = torch.from_numpy(self.acc.starts)  # first photon of each batch
        self.exit_fn = exit_function(self.compiled)
        self.exit_bins = ExitBins(
            radial_mm=radial_mm, sigma_t=self.sigma_t, batch_starts=self.batch_starts,
            n_theta=self.layout.n_theta, n_cos=self.layout.n_cos, n_phi=self.layout.n_phi, inv_eta=self.params.inv_eta,
        )  # fmt: skip
        self.vertex_buf: list[list[torch.Tensor]] = []
        self.vertex_count = 0
        self.steps = 0  # calls x steps per call
        self.photon_steps = 0  # interaction steps (free paths) of finished photons
        self.vertices = 0

    # -- lanes --------------------------------------------------------------------------------
    def finish_and_refill(self) -> tuple[int, int]:
        """Record the finished photons (walk totals; their exits must be tallied already) and
        launch the next photons into the lanes not running, in lane order; returns (photons
        finished, photons launched).  One pass over all the lanes (one compiled shape per lane
        count): in the tail, where only the first chunk runs, the rest are EMPTY and cost little."""
        launch = torch.tensor([self.start, self.next_launch, self.n_launch, self.cfgs.n], dtype=torch.int64)
        key, absorbed, truncated, n_free, steps = self.finish_fn(self.lanes_list, self.table_tensors, launch, self.batch_starts)
        launched = min(int(n_free), self.n_launch - self.next_launch)
        self.next_launch += launched
        self.photon_steps += int(steps)
        finished = self.acc.finish_photons(key.numpy(), absorbed.numpy(), truncated.numpy()) if int(steps) else 0
        return finished, launched

    def shrinkable(self, running: int) -> bool:
        """Whether compact() would step fewer lanes: nothing is left to launch and the running
        lanes fit in fewer chunks, or in the tail chunk."""
        if self.next_launch < self.n_launch:
            return False
        if running <= (self.active - 1) * self.chunk:
            return True
        return self.tail_chunk is not None and self.chunk != self.tail_chunk and running <= self.tail_chunk

    def compact(self, running: int) -> None:
        """Tail of the shard (nothing left to launch): move the running lanes, in lane order, to
        the front so that only ceil(running / chunk) chunks are stepped, and once they fit in
        the tail chunk, step that alone."""
        if not self.shrinkable(running):
            return
        n = self.active * self.chunk
        idx = torch.nonzero(self.lanes.status[:n] == RUNNING).squeeze(1)
        for t in self.lanes_list:
            t[: len(idx)] = t[idx]
        self.lanes.status[len(idx) : n] = EMPTY
        if self.tail_chunk is not None and self.chunk != self.tail_chunk and running <= self.tail_chunk:
            self.tail_lanes = running
            self.chunk = self.tail_chunk
            self.chunks = [[t[: self.chunk] for t in self.lanes_list]]
        self.active = max(1, math.ceil(running / self.chunk))

    def harvest(self, running: int) -> int:
        """Tally the lanes that finished, refill them; returns the lanes running afterwards."""
        if self.tally_exit_events:
            st = self.lanes.status[: self.active * self.chunk]
            self.tally_exits(torch.nonzero(st == EXITED).squeeze(1))
        finished, launched = self.finish_and_refill()
        if self.acc.ready:
            self.flush_vertices(force=True)  # a batch folds only after all its vertices are tallied
            self.acc.fold_ready()
        if self.progress is not None:
            self.progress(finished)
        running += launched
        self.compact(running)
        return running

    # -- exit estimator -------------------------------------------------------------------------
    def tally_exits(self, idx: torch.Tensor) -> None:
        """Tally the exit events of lanes idx (in lane order), EXIT_BLOCK at a time: the compiled
        lookup has one static shape, so the last block is padded with its first lane and cut."""
        n = len(idx)
        for a in range(0, n, EXIT_BLOCK):
            block = idx[a : a + EXIT_BLOCK]
            m = len(block)
            if m < EXIT_BLOCK and self.compiled:
                block = torch.cat((block, block[:1].expand(EXIT_BLOCK - m)))
            flat, batch, g, s = (v[:m].numpy() for v in self.exit_fn(block, self.lanes_list, self.exit_bins))
            self.acc.add_hist("exits", batch, flat, g, s)

    def flat_index(self, cfg, comp, spatial, direction) -> torch.Tensor:
        """Index into the flattened [cfg, comp, n_r + 1, n_theta, n_cos, n_phi] histogram."""
        n_dir = self.layout.n_cos * self.layout.n_phi
        n_sp = (self.layout.n_r + 1) * self.layout.n_theta
        return ((cfg * 2 + comp) * n_sp + spatial) * n_dir + direction

    # -- connection estimator -----------------------------------------------------------------
    def collect_vertices(self, vertex, offset: int) -> None:
        coll, ux, uy, uz, w = vertex
        local = torch.nonzero(coll).squeeze(1)
        idx = local + offset
        if len(idx) == 0:
            return
        L = self.lanes
        cols = [L.x[idx], L.y[idx], L.z[idx], ux[local], uy[local], uz[local], L.ux[idx], L.uy[idx], L.uz[idx], w[local],
                L.cfg[idx], L.photon[idx], L.step[idx] - 1, (L.nscat[idx] >= 2).to(torch.int64)]  # fmt: skip
        self.vertex_buf.append(cols)
        self.vertex_count += len(idx)
        self.vertices += len(idx)
        if self.vertex_count >= VERTEX_CHUNK:
            self.flush_vertices(force=False)

    def flush_vertices(self, force: bool) -> None:
        if not self.vertex_buf:
            return
        cols = [torch.cat(c) for c in zip(*self.vertex_buf)]
        self.vertex_buf, self.vertex_count = [], 0
        n = len(cols[0])
        for a in range(0, n, VERTEX_CHUNK):
            b = min(n, a + VERTEX_CHUNK)
            if b - a < VERTEX_CHUNK and not force:
                self.vertex_buf, self.vertex_count = [[c[a:] for c in cols]], n - a
                return
            self.connect_chunk([c[a:b] for c in cols])

    def connect_chunk(self, cols: list[torch.Tensor]) -> None:
        """Tally both connection techniques for up to VERTEX_CHUNK vertices.

        A short chunk is padded to VERTEX_CHUNK (the compiled kernel has one static shape) with
        copies of its first vertex, whose results are cut off before tallying.
        """
        n = len(cols[0])
        if n < VERTEX_CHUNK:
            cols = [torch.cat((c, c[:1].expand(VERTEX_CHUNK - n, *c.shape[1:]))) for c in cols]
        px, py, pz, ux, uy, uz, vx, vy, vz, w, cfg, photon, draw, comp = cols
        T = self.cfgs.table
        albedo, g, k0, k1 = T.albedo[cfg], T.g[cfg], T.k0[cfg], T.k1[cfg]
        c_lo, c_hi = photon_words(photon)
        (Gu, Su, spu, dru), (Gp, Sp, spp, drp) = self.connect_fn(
            px, py, pz, ux, uy, uz, vx, vy, vz, w, albedo, g, cfg, c_lo, c_hi, draw, k0, k1, self.geo
        )
        cfg, comp, photon = cfg[:n], comp[:n], photon[:n]
        batch = self.acc.batch_of(photon.numpy())
        flat = self.flat_index(cfg[:, None], comp[:, None], spu[:n], dru[:n])
        nb = flat.shape[1]
        self.acc.add_hist("connections", np.repeat(batch, nb), flat.reshape(-1).numpy(),
                          Gu[:n].reshape(-1).double().numpy(), Su[:n].reshape(-1).double().numpy())  # fmt: skip
        flat = self.flat_index(cfg, comp, spp[:n], drp[:n])
        self.acc.add_hist("connections", batch, flat.numpy(), Gp[:n].double().numpy(), Sp[:n].double().numpy())

    # -- main loop ------------------------------------------------------------------------------
    def run(self) -> ShardTally:
        t0 = time.perf_counter()
        with torch.no_grad():  # also around the first refill: grad mode is part of a compiled graph's key
            return self._run(t0)

    def _run(self, t0: float) -> ShardTally:
        running = self.finish_and_refill()[1]
        n_steps = 1 if self.connect else EXIT_STEPS_PER_CALL
        # Harvesting costs a pass over the lanes plus Python work: wait until an eighth of the
        # lanes has finished (or none runs) so the cost is spread over many photons.
        harvest_at = max(1, len(self.lanes.status) // HARVEST_DIVISOR)
        while running > 0:
            running = finished = 0
            for k in range(self.active):
                counts, vertex = self.step(self.chunks[k])
                running, finished = running + int(counts[0]), finished + int(counts[1])
                if self.connect:
                    self.collect_vertices(vertex, k * self.chunk)
            self.steps += n_steps
            if finished >= harvest_at or (running == 0 and finished > 0) or (finished and self.shrinkable(running)):
                running = self.harvest(running)
        self.flush_vertices(force=True)
        self.acc.fold_ready()
        assert self.acc.complete, "every batch must have folded once all photons finished"
        info = {
            "photons": self.n_launch, "lanes": len(self.lanes.status), "lane_steps": self.steps, "photon_steps": self.photon_steps,
            "vertices": self.vertices, "tail_lanes": self.tail_lanes, "elapsed_s": time.perf_counter() - t0,
            "engine": "compiled" if self.compiled else "eager", "torch": torch.__version__,
        }  # fmt: skip
        return ShardTally(-1, self.acc.stats, self.acc.n_sum, self.acc.nn_sum, self.acc.k, info)


def run_shard(spec: SimulationSpec, shard_index: int, *, progress: Callable[[int], None] | None = None) -> ShardTally:
    """Simulate shard `shard_index` of `spec`; a pure function of its inputs.

    progress, if given, is called with the number of photons (all configurations) finished since
    the last call.  The statistics in the result do not depend on the machine, the thread count
    or when the shard runs; `info` carries timings and counters that do.
    """
    init_engine()
    tally = _Runner(spec, shard_index, progress).run()
    tally.shard_index = shard_index
    return tally
