"""The vectorized random walk: photon lanes, one step, refill of finished lanes.

A fixed array of *lanes* holds photons in flight.  :func:`walk_step` advances every running lane
by one interaction (fly, hit the boundary or collide, Fresnel, absorb / roulette, scatter) with
masks and no Python branching on values, so torch.compile fuses it into a few passes over memory;
finished lanes keep their final state until the shard runner harvests them and refills the lane
with the next photon (:func:`refill_at`, run by :func:`workers.walk.harvest.harvest_block`).  All lengths are optical (sigma_t = 1, see
:mod:`workers.walk.conventions`), so one walk serves every channel and incidence angle at once.

Random numbers: each photon carries its own xoshiro128+ state (lanes r0..r3), started at launch
from Philox keyed by (seed, configuration) with counter (photon, 0) and advanced four outputs per
step (:mod:`workers.walk.rng`): a photon's path does not depend on its lane, the lane count or the
thread count.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, fields, replace
from functools import lru_cache

import torch

from .conventions import PURPOSE_WALK
from .kernels import compile_kernel
from .optics import fresnel_dielectric, sample_exponential, scatter_direction
from .phase import DEFAULT_PHASE, phase_function
from .path_roulette import round_outcome
from .rng import photon_words, stream_draws, stream_start, uniform_halfopen, uniform_open
from .stretch import stretch_factors

__all__ = ["RUNNING", "EXITED", "ABSORBED", "TRUNCATED", "EMPTY", "Lanes", "WalkParams", "ConfigTable", "STEP_FIELDS", "walk_step", "step_function", "refill_at", "compile_enabled", "walk_stream_start"]

# Lane status codes (int32: an int8 status made inductor convert masks element by element).
RUNNING = 0  # photon in flight
EXITED = 1  # refracted out through the surface; x, y and u hold the crossing
ABSORBED = 2  # killed by analog absorption or by Russian roulette
TRUNCATED = 3  # reached the path cap (max_scatter); w is the truncated weight
EMPTY = 4  # no photon: the shard has run out of photons to launch


@dataclass(frozen=True)
class WalkParams:
    """Scalars of a walk that are the same for every lane (compile-time constants).

    inv_eta: 1/eta, the relative index seen from inside at the surface.
    analog: absorption by killing with probability 1 - albedo (else weights + roulette).
    w_min, survival: Russian roulette: a weight below w_min survives with probability `survival`
    and is divided by it (unbiased: E[w'] = w).
    max_scatter: path cap in scattering events.
    """

    inv_eta: float
    analog: bool
    max_scatter: int
    w_min: float = 1e-3
    survival: float = 0.1
    hg_branch: str = "mixed"  # "large" / "small": every |g| >= 0.1 / < 0.1 (see sample_hg)
    phase: str = DEFAULT_PHASE  # the phase function (workers.walk.phase)
    stretch: tuple[float, float, float, float] | None = None  # radial path stretching (gamma, r_min, albedo_max, gamma_inward): workers.walk.stretch
    roulette: tuple[int, float] | None = None  # path-length roulette (start, survival) after each call's last step: workers.walk.path_roulette


@dataclass
class Lanes:
    """State of every lane, structure-of-arrays (one tensor per field, length = lane count)."""

    x: torch.Tensor  # float32 optical position
    y: torch.Tensor
    z: torch.Tensor
    ux: torch.Tensor  # float32 unit direction of travel
    uy: torch.Tensor
    uz: torch.Tensor
    w: torch.Tensor  # float32 weight (power) carried
    absorbed: torch.Tensor  # float32 weight deposited by absorption so far
    nscat: torch.Tensor  # int32 scattering events so far
    step: torch.Tensor  # int32 random draw index (steps taken)
    photon: torch.Tensor  # int64 photon index within its configuration
    cfg: torch.Tensor  # int64 configuration index (incidence angle x channel)
    status: torch.Tensor  # int32 status code
    albedo: torch.Tensor  # float32 per-lane copy of the configuration's albedo
    g: torch.Tensor  # float32 per-lane copy of the configuration's HG g
    k0: torch.Tensor  # int32 Philox key words of the configuration (bit patterns, workers.walk.rng)
    k1: torch.Tensor
    c_lo: torch.Tensor  # int32 Philox counter words 0 and 1: the photon index, low and high half
    c_hi: torch.Tensor
    r0: torch.Tensor  # int32 xoshiro128+ state of the photon's walk stream (workers.walk.rng)
    r1: torch.Tensor
    r2: torch.Tensor
    r3: torch.Tensor

    @classmethod
    def empty(cls, n: int) -> "Lanes":
        f32 = lambda: torch.zeros(n, dtype=torch.float32)  # noqa: E731
        i64 = lambda: torch.zeros(n, dtype=torch.int64)  # noqa: E731
        i32 = lambda: torch.zeros(n, dtype=torch.int32)  # noqa: E731
        return cls(
            x=f32(), y=f32(), z=f32(), ux=f32(), uy=f32(), uz=f32(), w=f32(), absorbed=f32(),
            nscat=i32(), step=i32(), photon=i64(), cfg=i64(),
            status=torch.full((n,), EMPTY, dtype=torch.int32),
            albedo=f32(), g=f32(), k0=i32(), k1=i32(), c_lo=i32(), c_hi=i32(), r0=i32(), r1=i32(), r2=i32(), r3=i32(),
        )  # fmt: skip

    def start_streams(self) -> None:
        """Start every lane's walk stream from its photon and key words (c_lo, c_hi, k0, k1), in
        place: what a launch does (:func:`refill_at`), for callers that set lanes up by hand."""
        for dst, val in zip((self.r0, self.r1, self.r2, self.r3), walk_stream_start(self.c_lo, self.c_hi, self.k0, self.k1)):
            dst.copy_(val)

    def tensors(self) -> list[torch.Tensor]:
        """Every field, in declaration order (for moves that treat all lanes' fields alike)."""
        return [getattr(self, f.name) for f in fields(self)]

    def view(self, start: int, stop: int) -> "Lanes":
        """Lanes [start, stop) as views: writes through a view change these lanes."""
        return Lanes(*(t[start:stop] for t in self.tensors()))

    def copy_from(self, other: "Lanes", names: tuple[str, ...]) -> None:
        """Write the fields `names` of other into these lanes, in place."""
        for name in names:
            getattr(self, name).copy_(getattr(other, name))


@dataclass(frozen=True)
class ConfigTable:
    """Per-configuration constants as tensors indexed by configuration (built by workers.run.plan)."""

    albedo: torch.Tensor  # float32
    g: torch.Tensor  # float32
    w0: torch.Tensor  # float32, 1 - R_spec
    ux0: torch.Tensor  # float32, refracted incident direction
    uz0: torch.Tensor
    k0: torch.Tensor  # int32 bit patterns
    k1: torch.Tensor


# The fields of a lane that a step changes; the others are fixed while its photon is in flight.
STEP_FIELDS = ("x", "y", "z", "ux", "uy", "uz", "w", "absorbed", "nscat", "step", "status", "r0", "r1", "r2", "r3")


def walk_stream_start(c_lo: torch.Tensor, c_hi: torch.Tensor, k0: torch.Tensor, k1: torch.Tensor):
    """The xoshiro128+ state a photon's walk starts from (int32 words): the Philox block of
    counter (photon, 0, PURPOSE_WALK) (:func:`workers.walk.rng.stream_start`).  Its first four
    outputs are the draws of the photon's first step (the hybrid's first vertex replays them)."""
    return stream_start(c_lo, c_hi, PURPOSE_WALK, k0, k1)


def walk_step(lanes: Lanes, *, p: WalkParams) -> tuple[Lanes, tuple[torch.Tensor, ...]]:
    """Advance every RUNNING lane by one interaction; returns the new state and vertex data.

    Four outputs of the photon's stream per step give u_path (free path), u_dec (Fresnel /
    roulette / absorption decision), u_cos and u_phi (scattering direction).  With s = -ln(u_path):
    - z + s uz >= 0: the path reaches the surface at t = -z/uz.  With probability
      Fr(uz, 1/eta) the photon reflects specularly (uz -> -uz) and continues from the surface
      (the free path is memoryless, so a fresh one is drawn next step); otherwise it exits.
    - otherwise: a collision at x + s u.  Weights mode: the absorbed share w (1 - albedo) is
      deposited and w *= albedo, then Russian roulette below w_min.  Analog mode: the photon is
      absorbed with probability 1 - albedo.  A surviving photon scatters into a new direction
      sampled from Henyey-Greenstein; after max_scatter scatterings it is truncated.
    - With ``p.stretch`` (workers.walk.stretch) s is drawn from sigma* exp(-sigma* s) instead and
      the weight takes the flight's likelihood ratio before the rest; roulette's threshold then
      falls with the distance from the axis.
    Returns the lanes after the step (new tensors for STEP_FIELDS, the others shared) and
    (collided, ux_in, uy_in, uz_in, w_in): the vertices of this step with the direction and
    weight arriving there, for the connection estimator.  The new direction is computed on every
    collided lane (also one killed afterwards), so it doubles as the phase-function sample of the
    connection's multiple importance sampling.
    """
    x, y, z, ux, uy, uz, w = lanes.x, lanes.y, lanes.z, lanes.ux, lanes.uy, lanes.uz, lanes.w
    status, step, albedo = lanes.status, lanes.step, lanes.albedo
    running = status == RUNNING
    # Every lane's stream advances (a lane not running is started afresh when it is refilled).
    (b0, b1, b2, b3), (r0, r1, r2, r3) = stream_draws((lanes.r0, lanes.r1, lanes.r2, lanes.r3))
    s = sample_exponential(uniform_open(b0))
    if p.stretch is not None:  # workers.walk.stretch: the free path drawn from sigma* exp(-sigma* s)
        gamma, r_min, albedo_max, gamma_in = p.stretch
        sig, gamma_mu = stretch_factors(x, y, ux, uy, lanes.nscat, albedo, running, gamma=gamma, r_min=r_min, albedo_max=albedo_max,
                                        gamma_inward=gamma_in)  # fmt: skip
        s = s / sig
    u_dec = uniform_halfopen(b1)
    z_new = z + s * uz
    hit = running & (z_new >= 0.0)
    coll = running & (z_new < 0.0)

    # Boundary: uz > 0 on hit lanes; elsewhere the distance is unused, the clamp avoids 0/0.
    t = -z / torch.clamp(uz, min=1e-30)
    if p.stretch is not None:  # the likelihood ratio of the flight, before absorption and Fresnel
        w = w * torch.where(hit, torch.exp(-gamma_mu * t), torch.where(coll, torch.exp(-gamma_mu * s) / sig, 1.0))
    reflect = hit & (u_dec < fresnel_dielectric(uz, p.inv_eta))
    escape = hit & ~reflect

    # Collision: absorption.
    if p.analog:
        killed = coll & (u_dec >= albedo)
        absorbed_new = lanes.absorbed + torch.where(killed, w, 0.0)
        w_new = w
    else:
        absorbed_new = lanes.absorbed + torch.where(coll, w * (1.0 - albedo), 0.0)
        w_att = torch.where(coll, w * albedo, w)
        if p.stretch is not None:  # roulette's threshold falls with distance as stretched weights do (workers.walk.stretch)
            xc, yc = x + s * ux, y + s * uy
            low = coll & (w_att < p.w_min * torch.exp(-gamma * torch.sqrt(xc * xc + yc * yc)))
        else:
            low = coll & (w_att < p.w_min)
        survive = u_dec < p.survival
        killed = low & ~survive
        w_new = torch.where(low, torch.where(survive, w_att * (1.0 / p.survival), 0.0), w_att)
    nscat_new = lanes.nscat + coll.to(torch.int32)
    truncated = coll & ~killed & (nscat_new >= p.max_scatter)

    # Collision: new direction (Henyey-Greenstein), on every collided lane.
    cos_t = phase_function(p.phase).sample_cos(uniform_halfopen(b2), lanes.g, p.hg_branch)
    phi = uniform_halfopen(b3) * (2.0 * torch.pi)
    nx, ny, nz = scatter_direction(ux, uy, uz, cos_t, phi)

    x_new = torch.where(hit, x + t * ux, torch.where(coll, x + s * ux, x))
    y_new = torch.where(hit, y + t * uy, torch.where(coll, y + s * uy, y))
    z_new = torch.where(hit, 0.0, torch.where(coll, z_new, z))
    ux_new = torch.where(coll, nx, ux)
    uy_new = torch.where(coll, ny, uy)
    uz_new = torch.where(coll, nz, torch.where(reflect, -uz, uz))
    status_new = torch.where(
        escape,
        EXITED,
        torch.where(killed, ABSORBED, torch.where(truncated, TRUNCATED, status)),
    )
    step_new = step + running.to(torch.int32)
    after = replace(
        lanes, x=x_new, y=y_new, z=z_new, ux=ux_new, uy=uy_new, uz=uz_new, w=w_new, absorbed=absorbed_new, nscat=nscat_new,
        step=step_new, status=status_new, r0=r0, r1=r1, r2=r2, r3=r3,
    )  # fmt: skip
    return after, (coll, ux, uy, uz, w)


def _step_inplace(lanes: Lanes, p: WalkParams, n_steps: int, want_vertices: bool):
    """Run n_steps steps writing the state back into `lanes` in place (with ``p.roulette``, then
    the path-length round of the lanes due: workers.walk.path_roulette).

    Returns (counts, vertex): counts = int64 [running, finished] lanes after the steps (finished =
    EXITED, ABSORBED or TRUNCATED, waiting for harvest); vertex = the last step's vertex data
    (collided, ux_in, uy_in, uz_in, w_in; see :func:`walk_step`) if want_vertices, else None.
    A tuple, not a dataclass: see :func:`workers.walk.kernels.compile_kernel` on results.
    """
    vertex = None
    cur = lanes
    for _ in range(n_steps):
        cur, vertex = walk_step(cur, p=p)
    # The arrival direction and weight are the old state, overwritten just below: copy them.  Not
    # wanted, they are not returned at all: a returned tensor is written on every call even if the
    # caller drops it (these 5 arrays cost a fifth of an M2 exit-walk call, BENCHMARKS.md).
    vertex = tuple(v.clone() for v in vertex) if want_vertices else None
    if p.roulette is not None:  # the path-length round of the lanes due, after the vertices of the last step
        start, survival = p.roulette
        w_round, ended = round_outcome(cur.status == RUNNING, cur.step, cur.w, cur.c_lo, cur.c_hi, cur.k0, cur.k1, start, survival)
        cur = replace(cur, w=w_round, status=torch.where(ended, ABSORBED, cur.status))
    lanes.copy_from(cur, STEP_FIELDS)
    new_status = cur.status
    counts = torch.stack(((new_status == RUNNING).sum(), ((new_status != RUNNING) & (new_status != EMPTY)).sum()))
    return counts, vertex


def refill_at(lanes: Lanes, table: ConfigTable, idx: torch.Tensor, pid: torch.Tensor, c: torch.Tensor, new: torch.Tensor, valid: torch.Tensor) -> None:
    """Launch photon pid[j] of configuration c[j] in lane idx[j] where new[j], in place; a lane
    idx[j] that is valid[j] but not new becomes EMPTY, its other fields undefined; padding
    positions (not valid) may write anything into their lane but its status.

    A new photon sits at the origin travelling along the refracted incident direction of its
    configuration with weight 1 - R_spec, its walk stream started (:func:`walk_stream_start`).
    Work and memory traffic are per index, not per lane: a harvest's refill costs what the
    finished photons cost, not what the lane array does (:func:`workers.walk.harvest.harvest_block`)."""
    L, T = lanes, table
    zero = torch.zeros(idx.shape, dtype=torch.float32)
    lo, hi = photon_words(pid)
    k0, k1 = T.k0[c], T.k1[c]
    r = walk_stream_start(lo, hi, k0, k1)
    values = ((L.x, zero), (L.y, zero), (L.z, zero), (L.uy, zero), (L.absorbed, zero),
              (L.ux, T.ux0[c]), (L.uz, T.uz0[c]), (L.w, T.w0[c]), (L.albedo, T.albedo[c]), (L.g, T.g[c]),
              (L.nscat, torch.zeros_like(lo)), (L.step, torch.zeros_like(lo)), (L.photon, pid), (L.c_lo, lo), (L.c_hi, hi),
              (L.cfg, c), (L.k0, k0), (L.k1, k1), (L.r0, r[0]), (L.r1, r[1]), (L.r2, r[2]), (L.r3, r[3]))  # fmt: skip
    for dst, val in values:  # unconditional: a lane that is not started is EMPTY or the scratch lane, whose fields no one reads
        dst[idx] = val
    L.status[idx] = torch.where(new, RUNNING, torch.where(valid, EMPTY, L.status[idx]))


def compile_enabled() -> bool:
    """Whether the walk runs through torch.compile (BSSRDF_COMPILE=0 selects the eager path).

    Both paths compute the same physics; they agree within error bars, not bitwise (the fused
    kernels round differently), so the mode is recorded with every result.
    """
    return os.environ.get("BSSRDF_COMPILE", "1") not in ("0", "false", "no")


@lru_cache(maxsize=None)
def step_function(p: WalkParams, n_steps: int, want_vertices: bool, compiled: bool):
    """The (possibly compiled) in-place stepping function for these constants."""

    def fn(lanes: Lanes):
        return _step_inplace(lanes, p, n_steps, want_vertices)

    return compile_kernel(fn, "walk_step", (p, n_steps, want_vertices), any_length=True) if compiled else fn
