"""The plan of a shard: everything fixed about running shard k of a spec, built once.

Configurations (incidence angle x channel) and their constants, the bin layout, the lane and
chunk sizes, the walk's constants and the tables the kernels read (:class:`ShardPlan`); the
mutable run that follows the plan is :mod:`workers.run.shard`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np
import torch

from schema import SimulationSpec

from workers.fold.configs import BinLayout, Configs, bin_layout, build_configs
from workers.fold.tally import TallyLayout
from workers.walk.connections import ConnectionGeometry
from workers.walk.harvest import ExitBins
from workers.walk.hybrid import K_SAMPLES, EntryLayout, FirstVertexGeometry
from workers.walk.optics import incident_refracted_direction
from workers.walk.phase import phase_of
from workers.walk.rng import stream_key, to_i32
from workers.walk.walk import ConfigTable, WalkParams, compile_enabled

__all__ = ["ShardPlan", "config_table", "chunk_count", "CHUNK", "VERTEX_CHUNK", "LANE_MULTIPLE", "TAIL_FILL", "HARVEST_DIVISOR"]

CHUNK = 1 << 14  # lanes per call of the compiled step (the tail's chunks are shorter: one kernel serves every length); 2^15 ran M1 ~30 % slower on a 512 KiB-L2 machine
EAGER_CHUNK = 1 << 12  # lanes per call on the eager path, which has no per-call overhead to hide
CONNECT_CHUNK = 1 << 11  # lanes per call with connections: their kernel dominates, few photons run
MAX_CHUNKS = 4  # 2^16 lanes in all: enough photons in flight to keep every chunk full
TAIL_FILL = 0.75  # the tail (nothing left to launch) is compacted to its running lanes once they fill no more than this of the stepped ones
PHOTONS_PER_LANE = 32  # launches per lane before using more chunks: keeps the tail short
VERTEX_CHUNK = 1 << 11  # vertices per connection kernel call
EXIT_STEPS_PER_CALL = 8  # steps per compiled call between harvests (exit estimator)
LANE_MULTIPLE = 16  # every length a compiled any-length kernel is called with is a multiple of this (the vector width)
HARVEST_DIVISOR = 8  # harvest once 1/HARVEST_DIVISOR of the lanes has finished (4 and 32 ran M1 slower here)


def config_table(spec: SimulationSpec, cfgs: Configs) -> ConfigTable:
    """The walk's per-configuration table (float32 optics, entry direction, Philox key) of the
    configurations ``cfgs`` of ``spec`` (:func:`workers.fold.configs.build_configs`)."""
    channels = spec.channels()
    rows = []
    for i_inc, theta in enumerate(spec.incidence_deg):
        ux0, _, uz0 = incident_refracted_direction(math.radians(theta), cfgs.eta)
        for i_ch, ch in enumerate(channels):
            fingerprint = json.dumps(
                [i_inc, theta, i_ch, ch.sigma_a, ch.sigma_s, ch.g, cfgs.eta], separators=(",", ":")
            )
            k0, k1 = stream_key(spec.seed, fingerprint)
            rows.append((ux0, uz0, k0, k1))
    ux0s, uz0s, k0s, k1s = zip(*rows)
    f32 = lambda v: torch.tensor(v, dtype=torch.float32)  # noqa: E731
    return ConfigTable(
        albedo=f32(cfgs.albedo.tolist()), g=f32(cfgs.g.tolist()), w0=f32([1.0 - r for r in cfgs.r_spec.tolist()]),
        ux0=f32(ux0s), uz0=f32(uz0s),
        k0=to_i32(torch.tensor(k0s, dtype=torch.int64)), k1=to_i32(torch.tensor(k1s, dtype=torch.int64)),
    )  # fmt: skip


def chunk_count(n_launch: int, chunk: int) -> int:
    """Chunks of `chunk` lanes for a shard: enough that each lane runs about PHOTONS_PER_LANE
    photons (fewer lanes keep the tail, where lanes fall idle, short), at most MAX_CHUNKS."""
    return int(min(MAX_CHUNKS, max(1, math.ceil(n_launch / (PHOTONS_PER_LANE * chunk)))))


@dataclass(frozen=True)
class ShardPlan:
    """Everything fixed about running shard `shard_index` of `spec`, built once (:meth:`build`).

    estimators: what is tallied ("exits", "connections", "hybrid"); connect: vertices are
    connected to every bin (1 step per call); exits: exit events are binned (exit tally or the
    hybrid's multiple scattering); first_vertex: the hybrid's first-vertex connections.
    chunk / n_lanes: lanes per step call and in all (a shard's tail steps fewer:
    workers.run.shard); n_steps: steps per call.
    """

    spec: SimulationSpec
    shard_index: int
    cfgs: Configs
    table: ConfigTable  # the walk's per-configuration constants (config_table)
    layout: BinLayout
    start: int
    stop: int
    estimators: tuple[str, ...]
    compiled: bool
    chunk: int
    n_lanes: int
    params: WalkParams
    n_steps: int
    geo: ConnectionGeometry
    exit_bins: ExitBins
    first_vertex: FirstVertexGeometry | None
    entry_layout: EntryLayout

    @property
    def n_launch(self) -> int:
        """Photons of the shard, all configurations."""
        return (self.stop - self.start) * self.cfgs.n

    @property
    def connect(self) -> bool:
        return "connections" in self.estimators

    @property
    def exits(self) -> bool:
        return "exits" in self.estimators or "hybrid" in self.estimators

    @classmethod
    def build(cls, spec: SimulationSpec, shard_index: int) -> "ShardPlan":
        cfgs, layout = build_configs(spec), bin_layout(spec)
        table = config_table(spec, cfgs)
        start, stop = spec.shard_photon_range(shard_index)
        estimators = spec.table_estimators
        compiled = compile_enabled()
        connect = "connections" in estimators
        chunk = CONNECT_CHUNK if connect else CHUNK if compiled else EAGER_CHUNK
        abs_g = np.abs(table.g.numpy())
        params = WalkParams(
            inv_eta=1.0 / cfgs.eta, analog=spec.absorption == "analog", max_scatter=spec.max_scatter,
            hg_branch="large" if (abs_g >= 0.1).all() else "small" if (abs_g < 0.1).all() else "mixed", phase=phase_of(spec),
            stretch=_stretch(spec, cfgs), roulette=None if spec.path_roulette is None else (spec.path_roulette.start, spec.path_roulette.survival),
        )  # fmt: skip
        sigma_t = torch.tensor(cfgs.sigma_t, dtype=torch.float64)
        radial_mm = torch.from_numpy(layout.radial_mm[[cfgs.channel_of(c) for c in range(cfgs.n)]])  # [cfg, n_r + 1]
        edges_opt = radial_mm * sigma_t[:, None]
        counts = dict(n_theta=layout.n_theta, n_cos=layout.n_cos, n_phi=layout.n_phi)
        geo = ConnectionGeometry(
            r_lo=edges_opt[:, :-1].to(torch.float32).contiguous(), r_hi=edges_opt[:, 1:].to(torch.float32).contiguous(), eta=cfgs.eta, phase=params.phase, **counts,
        )  # fmt: skip
        starts = torch.tensor([a for a, _ in spec.batch_photon_ranges(shard_index)], dtype=torch.int64)
        exit_bins = ExitBins(radial_mm=radial_mm, sigma_t=sigma_t, batch_starts=starts, inv_eta=params.inv_eta, **counts)
        first_vertex = None
        if "hybrid" in estimators:
            t = table
            first_vertex = FirstVertexGeometry(
                edges=edges_opt.to(torch.float32).contiguous(), u0x=t.ux0, u0z=t.uz0, w0=t.w0, albedo=t.albedo,
                g=t.g, k0=t.k0, k1=t.k1, eta=cfgs.eta, k=min(K_SAMPLES, layout.n_r * layout.n_theta), hg_branch=params.hg_branch, phase=params.phase, **counts,
            )  # fmt: skip
        n_lanes = chunk_count((stop - start) * cfgs.n, chunk) * chunk
        n_sp, n_dir = (layout.n_r + 1) * layout.n_theta, layout.n_cos * layout.n_phi
        offsets = tuple(int(o) for o in TallyLayout(cfgs.n, layout.shape).square_offsets[:4])
        entry_layout = EntryLayout(n_sp=n_sp, n_dir=n_dir, n_theta=layout.n_theta, square_offsets=offsets)
        return cls(
            spec=spec, shard_index=shard_index, cfgs=cfgs, table=table, layout=layout, start=start, stop=stop, estimators=estimators,
            compiled=compiled, chunk=chunk, n_lanes=n_lanes,
            params=params, n_steps=1 if connect else EXIT_STEPS_PER_CALL, geo=geo, exit_bins=exit_bins, first_vertex=first_vertex,
            entry_layout=entry_layout,
        )  # fmt: skip


def _stretch(spec: SimulationSpec, cfgs: Configs) -> tuple[float, float, float, float] | None:
    """The walk's radial path stretching (gamma, r_min, albedo_max, gamma_inward) (workers.walk.stretch), None
    without the spec's ``stretch`` or when no configuration's albedo is below its albedo_max: then
    the compiled step has no stretching code at all (the walks at albedo >= albedo_max of a sweep
    run as fast as without it)."""
    st = spec.stretch
    if st is None or not any(float(a) < st.albedo_max for a in cfgs.albedo):
        return None
    return (st.gamma, st.r_min_mfp, st.albedo_max, st.inward())
