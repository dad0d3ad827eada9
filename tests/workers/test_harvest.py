"""The exit tally's lookup (workers.walk.harvest) against the reference lookups of workers.walk.binning
(torch.searchsorted / bucketize on the stored edges), and the compiled kernel against the eager
function, bit for bit."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from schema import azimuth_edges, uniform_edges
from tests.reference.binning import searched
from workers.fold.configs import BinLayout
from workers.walk.binning import outgoing_azimuth
from workers.walk.harvest import ExitBins, batch_index, exit_bins
from workers.walk.optics import refracted_cos
from workers.walk.walk import EMPTY, EXITED, RUNNING, Lanes

TWO_PI = 2.0 * math.pi


@pytest.mark.parametrize("n_batches", [1, 4, 16, 17, 1024])
def test_batch_index_is_searchsorted(n_batches):
    starts = torch.arange(n_batches, dtype=torch.int64) * 37 + 1000
    photon = torch.arange(1000, 1000 + 37 * n_batches + 5)
    want = np.searchsorted(starts.numpy(), photon.numpy(), side="right") - 1
    assert np.array_equal(batch_index(photon, starts).numpy(), want)


N_R, N_THETA, N_COS, N_PHI = 7, 3, 5, 4
STARTS = [100, 130, 161, 190]  # batches of the shard: photons [100, 130), [130, 161), ...


def _bins(eta: float = 1.3) -> tuple[ExitBins, BinLayout, np.ndarray]:
    radial = np.stack([np.concatenate(([0.0], np.geomspace(0.05, 2.0, N_R))), np.linspace(0.0, 3.0, N_R + 1)])
    layout = BinLayout(radial, azimuth_edges(N_THETA), uniform_edges(0.0, 1.0, N_COS), azimuth_edges(N_PHI))
    sigma_t = np.array([2.0, 0.7, 1.3])  # three configurations: channels 0, 1, 0
    channel = np.array([0, 1, 0])
    bins = ExitBins(
        radial_mm=torch.from_numpy(radial[channel]), sigma_t=torch.from_numpy(sigma_t),
        batch_starts=torch.tensor(STARTS), n_theta=N_THETA, n_cos=N_COS, n_phi=N_PHI, inv_eta=1.0 / eta,
    )  # fmt: skip
    return bins, layout, channel


def _lanes(n: int, bins: ExitBins, seed: int = 5):
    """Random lanes of every status; exit positions include points exactly on radial edges."""
    gen = torch.Generator().manual_seed(seed)
    f32 = lambda *shape: torch.rand(*shape, generator=gen, dtype=torch.float32)  # noqa: E731
    cfg = torch.randint(0, 3, (n,), generator=gen)
    r = f32(n) * 4.0
    on_edge = torch.arange(n) % 5 == 0
    edge = bins.radial_mm[cfg, torch.randint(0, N_R + 1, (n,), generator=gen)] * bins.sigma_t[cfg]
    r = torch.where(on_edge, edge.float(), r)
    a = f32(n) * TWO_PI
    x, y = r * torch.cos(a), r * torch.sin(a)
    x[0], y[0] = 0.0, 0.0  # exit at the origin
    # Directions that refract out (a walk's exits): uz above the critical cosine of eta = 1.3.
    uz_c = math.sqrt(1.0 - bins.inv_eta**2)
    uz = uz_c + (1.0 - uz_c) * (0.001 + 0.999 * f32(n))
    b = f32(n) * TWO_PI
    sin_t = torch.sqrt(1.0 - uz * uz)
    u = torch.stack((sin_t * torch.cos(b), sin_t * torch.sin(b), uz), dim=1)
    u[1] = torch.tensor([0.0, 0.0, 1.0])  # straight up
    lanes = dict(
        x=x, y=y, ux=u[:, 0].contiguous(), uy=u[:, 1].contiguous(), uz=u[:, 2].contiguous(),
        w=f32(n), absorbed=f32(n), nscat=torch.randint(0, 4, (n,), generator=gen, dtype=torch.int32),
        photon=torch.randint(STARTS[0], 220, (n,), generator=gen), cfg=cfg,
        status=torch.randint(0, 5, (n,), generator=gen, dtype=torch.int32),
        step=torch.randint(0, 1000, (n,), generator=gen, dtype=torch.int32),
    )  # fmt: skip
    return lanes


def _reference(lanes: dict, layout: BinLayout, channel: np.ndarray, bins: ExitBins):
    """Flat index, G and S of every exit by the searchsorted / bucketize lookups on float64."""
    cfg = lanes["cfg"]
    x, y = lanes["x"].double(), lanes["y"].double()
    ux, uy, uz = (lanes[k].double() for k in ("ux", "uy", "uz"))
    r_mm = torch.sqrt(x * x + y * y) / bins.sigma_t[cfg]
    ir = searched(layout).radial_index(r_mm, torch.from_numpy(channel)[cfg])
    it = searched(layout).theta_index(torch.where((x == 0) & (y == 0), 0.0, torch.atan2(y, x)))  # theta_s = 0 at r = 0
    cos_o = refracted_cos(uz, bins.inv_eta)  # > 0: exits refract out
    ic = searched(layout).cos_index(cos_o)
    ip = searched(layout).phi_index(outgoing_azimuth(x, y, ux, uy))
    comp = (lanes["nscat"] >= 2).to(torch.int64)
    flat = ((cfg * 2 + comp) * ((N_R + 1) * N_THETA) + ir * N_THETA + it) * (N_COS * N_PHI) + ic * N_PHI + ip
    w = lanes["w"].double()
    return flat, w, w / cos_o


def _as_lanes(lanes: dict) -> Lanes:
    """The fields of `lanes` in a Lanes of their length (the others zero)."""
    full = Lanes.empty(len(lanes["x"]))
    for name, value in lanes.items():
        getattr(full, name).copy_(value)
    return full


def _exit_bins(lanes: dict, idx: torch.Tensor, bins: ExitBins):
    return exit_bins(idx, _as_lanes(lanes), bins)


def test_exit_bins_match_the_reference_lookups():
    bins, layout, channel = _bins()
    lanes = _lanes(20_000, bins)
    idx = torch.nonzero(lanes["status"] == EXITED).squeeze(1)
    assert len(idx) > 3000
    flat, batch, g, s = _exit_bins(lanes, idx, bins)
    ref_flat, ref_g, ref_s = (v[idx] for v in _reference(lanes, layout, channel, bins))
    assert torch.equal(flat, ref_flat)
    assert torch.equal(g, ref_g)
    assert torch.equal(s, ref_s)
    # Every radial bin and the overflow ring, every theta_s and direction bin, both components
    # and every configuration were hit: the comparison covers them all.
    n_dir = N_COS * N_PHI
    assert set(((flat // (N_THETA * n_dir)) % (N_R + 1)).tolist()) == set(range(N_R + 1))
    assert set(((flat // n_dir) % N_THETA).tolist()) == set(range(N_THETA))
    assert set((flat % n_dir).tolist()) == set(range(n_dir))
    assert set((flat // ((N_R + 1) * N_THETA * n_dir)).tolist()) == set(range(6))
    want_batch = np.searchsorted(np.array(STARTS), lanes["photon"][idx].numpy(), side="right") - 1
    assert np.array_equal(batch.numpy(), want_batch)
    assert set(want_batch.tolist()) == {0, 1, 2, 3}


HARVEST_N, HARVEST_CFG, HARVEST_BLOCK = 4000, 3, 512


def _harvest(lanes: dict, compiled: bool, launches_short: int = 100, exits: bool = True, members: bool = True):
    """The shard runner's harvest on `lanes` (plus a scratch lane): harvest_block over blocks of
    the lanes not running, the last padded with the scratch lane.  Returns the lanes after, the
    records by name (harvest_fields) concatenated over the blocks (steps: summed), the free
    lanes, the config table and launch = (start, next, end)."""
    from workers.measure.bench import _spec
    from workers.fold.configs import build_configs
    from workers.run.plan import config_table
    from workers.walk.harvest import harvest_fields, harvest_function

    n = len(lanes["x"])
    full = _as_lanes({k: torch.cat((v, v[:1])) for k, v in lanes.items()})  # lane n: the scratch lane
    spec = _spec("M2", "exits", 1000).model_copy(update={"incidence_deg": [0.0, 30.0, 60.0]})
    table = config_table(spec, build_configs(spec))
    idx = torch.nonzero(lanes["status"] != RUNNING).squeeze(1)
    start, nxt, end = 5000, 7, 7 + len(idx) - launches_short
    fn, bins = harvest_function(compiled, exits, members), _bins()[0]
    names = harvest_fields(exits, members)
    outs = []
    with torch.no_grad():
        for a in range(0, len(idx), HARVEST_BLOCK):
            block = idx[a : a + HARVEST_BLOCK]
            m = len(block)
            block = torch.cat((block, torch.full((HARVEST_BLOCK - m,), n, dtype=torch.int64)))
            launch = torch.tensor([start, nxt + a, end, HARVEST_CFG])
            out = fn(block, torch.tensor(m), full, table, launch, bins)
            assert len(out) == len(names)
            outs.append([v if name == "steps" else v[:m] for name, v in zip(names, out)])
    records = {name: (sum(v) if name == "steps" else torch.cat(v)) for name, v in zip(names, zip(*outs))}
    return full, records, idx, table, (start, nxt, end)


def test_harvest_block_records_lanes_and_refills_them_in_lane_order():
    """Against a per-lane reference: for every lane not running, the key (batch, configuration),
    absorbed / truncated weight and steps of a finished photon (spare key and zeros otherwise),
    the exit entry (flat, G, S) of an exited one (zeros otherwise) and its state; then the
    refill: the k-th free lane gets launch number next + k until the launches run out (photon,
    configuration, entry state, its walk stream started), the rest become EMPTY, running lanes
    and the padding's scratch lane keep their state."""
    from workers.walk.walk import TRUNCATED, walk_stream_start
    from workers.walk.harvest import exit_bins, spread_bins, spread_mask

    bins, _, _ = _bins()
    lanes = _lanes(HARVEST_N, bins, seed=17)
    before = {name: value.clone() for name, value in lanes.items()}
    full, rec, idx, table, (start, nxt, end) = _harvest(lanes, compiled=False)
    flat, g, s, key, absorbed, truncated, steps, status, nscat, w = (rec[k] for k in ("flat", "g", "s", "key", "absorbed", "truncated", "steps", "status", "nscat", "w"))
    n_cfg, st = HARVEST_CFG, before["status"][idx]
    done = (st != RUNNING) & (st != EMPTY)
    assert len(idx) > 2000 and int(done.sum()) > 1000 and int((st == EMPTY).sum()) > 300

    batch = torch.from_numpy(np.searchsorted(np.array(STARTS), before["photon"][idx].numpy(), side="right") - 1)
    assert torch.equal(key, torch.where(done, batch * n_cfg + before["cfg"][idx], len(STARTS) * n_cfg))
    assert torch.equal(absorbed, torch.where(done, before["absorbed"][idx].double(), 0.0))
    assert torch.equal(truncated, torch.where(st == TRUNCATED, before["w"][idx].double(), 0.0))
    assert steps.dtype == torch.int64 and int(steps) == int(before["step"][idx][done].sum())
    assert torch.equal(status, st) and torch.equal(nscat, before["nscat"][idx]) and torch.equal(w, before["w"][idx])
    ex = st == EXITED
    ref_flat, _, ref_g, ref_s = exit_bins(idx[ex], _as_lanes(before), bins)
    assert torch.equal(flat[ex], ref_flat) and torch.equal(g[ex], ref_g) and torch.equal(s[ex], ref_s)
    # Zeros spread over configuration 0's bins by position in the block (harvest.spread_mask), where they change no sum.
    spread = torch.arange(len(idx)) % HARVEST_BLOCK & spread_mask(spread_bins(bins))
    assert spread_bins(bins) == 2 * (N_R + 1) * N_THETA * N_COS * N_PHI and int(spread.max()) == HARVEST_BLOCK - 1
    assert [spread_mask(n) for n in (1, 2, 3, 4, 959, 960, 1024, 1025)] == [0, 1, 1, 3, 511, 511, 1023, 1023]
    assert torch.equal(flat[~ex], spread[~ex]) and bool((g[~ex] == 0).all()) and bool((s[~ex] == 0).all())

    q = nxt + torch.arange(len(idx))
    new, idle, qn = idx[q < end], idx[q >= end], q[q < end]
    c = qn % n_cfg
    assert torch.equal(full.photon[new], start + qn // n_cfg) and torch.equal(full.cfg[new], c)
    assert bool((full.status[new] == RUNNING).all()) and bool((full.step[new] == 0).all()) and bool((full.nscat[new] == 0).all())
    assert torch.equal(full.w[new], table.w0[c]) and torch.equal(full.uz[new], table.uz0[c]) and torch.equal(full.ux[new], table.ux0[c])
    for name in ("x", "y", "z", "uy", "absorbed"):
        assert bool((getattr(full, name)[new] == 0).all()), name
    stream = walk_stream_start(full.c_lo[new], full.c_hi[new], table.k0[c], table.k1[c])
    assert all(torch.equal(getattr(full, f"r{i}")[new], stream[i]) for i in range(4))
    assert len(idle) == 100 and bool((full.status[idle] == EMPTY).all())
    running = before["status"] == RUNNING
    for name in before:
        assert torch.equal(getattr(full, name)[:HARVEST_N][running], before[name][running]), name
    assert int(full.status[HARVEST_N]) == int(before["status"][0])  # the scratch lane's status is never written


@pytest.mark.parametrize("exits, members", [(False, True), (True, False), (False, False)])
def test_harvest_without_the_exit_tally_or_members_records_and_refills_the_same_with_fewer_records(exits, members):
    """A run without the exit tally (the hybrid alone) skips the exit lookup and one without
    reweighted members their records: the kernel returns only harvest_fields(exits, members),
    each equal to the full harvest's, and every lane after the refill is the full harvest's."""
    from workers.walk.harvest import harvest_fields

    lanes = _lanes(HARVEST_N, _bins()[0], seed=23)
    full, rec, _, _, _ = _harvest({k: v.clone() for k, v in lanes.items()}, compiled=False)
    bare, rec_bare, _, _, _ = _harvest({k: v.clone() for k, v in lanes.items()}, compiled=False, exits=exits, members=members)
    assert list(rec) == ["flat", "g", "s", "key", "absorbed", "truncated", "steps", "status", "nscat", "w"]
    assert set(rec_bare) == {"key", "absorbed", "truncated", "steps"} | ({"flat", "g", "s"} if exits else set()) | (
        {"status", "nscat", "w"} if members else set())  # fmt: skip
    assert list(rec_bare) == list(harvest_fields(exits, members))
    assert all(torch.equal(rec[name], value) for name, value in rec_bare.items())
    assert (rec["flat"] != 0).any() and (rec["g"] != 0).any()
    assert all(torch.equal(a, b) for a, b in zip(full.tensors(), bare.tensors()))


_COMPILED_SCRIPT = """
import json
import torch
from dataclasses import fields
from tests.workers.test_harvest import _bins, _lanes, _harvest
from workers.walk.walk import Lanes

torch.set_num_threads(1)
lanes = _lanes(4000, _bins()[0], seed=13)
eager, rec_e, _, _, _ = _harvest({k: v.clone() for k, v in lanes.items()}, compiled=False)
compiled, rec_c, _, _, _ = _harvest({k: v.clone() for k, v in lanes.items()}, compiled=True)
same = [bool(torch.equal(rec_e[k], rec_c[k])) for k in rec_e]
same_lanes = [f.name for f in fields(Lanes) if not torch.equal(getattr(eager, f.name)[:4000], getattr(compiled, f.name)[:4000])]
print(json.dumps([same, same_lanes, float(((rec_c["s"] - rec_e["s"]) / torch.where(rec_e["s"] == 0, 1.0, rec_e["s"])).abs().max())]))
"""


@pytest.mark.slow
def test_compiled_harvest_agrees_with_the_eager_one():
    """The compiled harvest block records and refills as the eager function does: every record
    and every lane exactly, but S = w / cos_o to float64 rounding (inductor multiplies by
    reciprocals of constants and contracts to FMA)."""
    env = dict(os.environ, BSSRDF_COMPILE="1")
    root = Path(__file__).resolve().parents[2]
    proc = subprocess.run([sys.executable, "-c", _COMPILED_SCRIPT], cwd=root, env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-4000:]
    same, lanes_differing, s_rel = json.loads(proc.stdout.strip().splitlines()[-1])
    names = ["flat", "G", "S", "key", "absorbed", "truncated", "steps", "status", "nscat", "w"]
    assert len(same) == len(names) and all(ok for n, ok in zip(names, same) if n != "S"), [n for n, ok in zip(names, same) if not ok]
    assert lanes_differing == [] and s_rel < 1e-14
