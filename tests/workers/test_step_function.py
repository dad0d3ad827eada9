"""The in-place step function's results: lane counts, and the last step's vertices only when asked.

Every array a compiled call returns is written on every call, read or not: the exit walk's call
once returned the last step's five vertex arrays, which only the connection estimator reads,
and writing them cost a fifth of the call (BENCHMARKS.md).  So the contract is checked here.
"""

from __future__ import annotations

import torch

from workers.walk.walk import EMPTY, RUNNING, Lanes, WalkParams, step_function

N = 2048


def _lanes() -> Lanes:
    """N photons in flight half a mean free path under the surface of a medium of albedo 0.9, half
    of them heading up, a quarter of the lanes empty."""
    lanes = Lanes.empty(N)
    lanes.status[:] = RUNNING
    lanes.status[::4] = EMPTY
    lanes.photon[:] = torch.arange(N)
    lanes.c_lo[:] = torch.arange(N, dtype=torch.int32)
    lanes.k0[:], lanes.k1[:] = 2024, -99
    lanes.z[:], lanes.uz[:], lanes.w[:], lanes.albedo[:] = -0.5, -1.0, 1.0, 0.9
    lanes.uz[1::2] = 1.0  # half of them head for the surface
    lanes.start_streams()
    return lanes


def test_without_vertices_the_call_returns_the_lane_counts_and_no_vertex_arrays():
    params = WalkParams(inv_eta=1.0 / 1.33, analog=False, max_scatter=1 << 20)
    lanes = _lanes()
    counts, vertex = step_function(params, 8, False, False)(lanes)
    assert vertex is None
    status = lanes.status
    assert counts.dtype == torch.int64 and counts.tolist() == [int((status == RUNNING).sum()), int(((status != RUNNING) & (status != EMPTY)).sum())]
    assert counts[0] > 0 and counts[1] > 0 and int(counts.sum()) == N - N // 4  # some photons finished in 8 steps; the empty lanes are neither


def test_with_vertices_the_call_returns_the_last_steps_collisions_with_their_arrival_state():
    """One step: the vertices are the lanes that collided, with the direction and weight they
    arrived with (the state before the step), copied before the lanes are overwritten."""
    params = WalkParams(inv_eta=1.0 / 1.33, analog=False, max_scatter=1 << 20)
    lanes = _lanes()
    before = Lanes(*(t.clone() for t in lanes.tensors()))
    _, (collided, ux_in, uy_in, uz_in, w_in) = step_function(params, 1, True, False)(lanes)
    running = before.status == RUNNING
    assert bool((collided <= running).all()) and 0 < int(collided.sum()) < int(running.sum())  # some reach the surface instead
    for got, start in ((ux_in, before.ux), (uy_in, before.uy), (uz_in, before.uz), (w_in, before.w)):
        assert torch.equal(got[collided], start[collided])
    assert torch.equal(lanes.nscat[collided], before.nscat[collided] + 1)  # the lanes themselves moved on
    assert not torch.equal(lanes.uz[collided], before.uz[collided])
