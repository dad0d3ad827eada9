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
from workers.walk.harvest import ExitBins, batch_index, count_le, exit_bins
from workers.walk.optics import refracted_cos
from workers.walk.walk import EMPTY, EXITED, Lanes

TWO_PI = 2.0 * math.pi


@pytest.mark.parametrize("m", [1, 2, 3, 5, 8, 49, 64, 65])
def test_count_le_is_searchsorted_right(m):
    """Every value of a row, each just below and above, and values outside the row."""
    gen = torch.Generator().manual_seed(m)
    table = torch.sort(torch.rand(3, m, generator=gen, dtype=torch.float64) * 10.0, dim=1).values
    table[1, : m // 2] = table[1, 0]  # repeated edges
    for row in range(3):
        r = table[row]
        values = torch.cat((r, torch.nextafter(r, r - 1), torch.nextafter(r, r + 1), torch.tensor([-1.0, 0.0, 11.0, 1e300])))
        rows = torch.full(values.shape, row, dtype=torch.int64)
        want = torch.searchsorted(r, values, right=True)
        assert torch.equal(count_le(table, rows, values), want)


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
    it = searched(layout).theta_index(torch.atan2(y, x))
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


def test_finish_and_refill_records_finished_photons_and_refills_in_lane_order():
    """Against a per-lane reference: the key (batch, configuration) and the absorbed / truncated
    weights of exactly the finished lanes, the count of free lanes and the steps of finished
    photons; then the refill: free lanes get launch numbers in lane order until the launches
    run out, the rest become EMPTY, running lanes are untouched."""
    from workers.measure.bench import _spec
    from workers.walk.harvest import finish_and_refill
    from workers.fold.configs import build_configs
    from workers.run.plan import config_table
    from workers.walk.walk import RUNNING, TRUNCATED

    bins, _, _ = _bins()
    n, n_cfg = 4000, 3
    lanes = _lanes(n, bins, seed=17)
    full = _as_lanes(lanes)
    before = {name: value.clone() for name, value in lanes.items()}
    st = before["status"]
    done = (st != RUNNING) & (st != EMPTY)
    free = st != RUNNING
    spec = _spec("M2", "exits", 1000).model_copy(update={"incidence_deg": [0.0, 30.0, 60.0]})
    table = config_table(spec, build_configs(spec))
    start, nxt, left = 5000, 7, int(free.sum()) - 100  # the last 100 free lanes get nothing
    launch = torch.tensor([start, nxt, nxt + left, n_cfg])
    key, absorbed, truncated, n_free, steps = finish_and_refill(full, table, launch, bins.batch_starts)

    batch = torch.from_numpy(np.searchsorted(np.array(STARTS), before["photon"].numpy(), side="right") - 1)
    assert torch.equal(key, torch.where(done, batch * n_cfg + before["cfg"], len(STARTS) * n_cfg))
    assert torch.equal(absorbed, torch.where(done, before["absorbed"].double(), 0.0))
    assert torch.equal(truncated, torch.where(st == TRUNCATED, before["w"].double(), 0.0))
    assert int(n_free) == int(free.sum()) and int(steps) == int(before["step"][done].sum())

    q = nxt + torch.arange(int(free.sum()))
    lane = torch.nonzero(free).squeeze(1)
    new, idle = lane[q < nxt + left], lane[q >= nxt + left]
    qn = q[q < nxt + left]
    assert torch.equal(full.photon[new], start + qn // n_cfg) and torch.equal(full.cfg[new], qn % n_cfg)
    assert bool((full.status[new] == RUNNING).all()) and bool((full.step[new] == 0).all())
    assert torch.equal(full.w[new], table.w0[qn % n_cfg]) and torch.equal(full.uz[new], table.uz0[qn % n_cfg])
    assert len(idle) == 100 and bool((full.status[idle] == EMPTY).all())
    running = ~free
    for name in ("x", "y", "uz", "w", "absorbed", "photon", "cfg", "step", "status"):
        assert torch.equal(getattr(full, name)[running], before[name][running]), name


_COMPILED_SCRIPT = """
import json
import torch
from tests.workers.test_harvest import _bins, _lanes, _block
from workers.walk.walk import EXITED

torch.set_num_threads(1)
bins, _, _ = _bins()
lanes = _lanes(6000, bins, seed=13)
idx = torch.nonzero(lanes["status"] == EXITED).squeeze(1)[:2048]
eager = _block(lanes, idx, bins, compiled=False)
compiled = _block(lanes, idx, bins, compiled=True)
same = [bool(torch.equal(a, b)) for a, b in zip(eager, compiled)]
print(json.dumps(same + [float(((compiled[3] - eager[3]) / eager[3]).abs().max())]))
"""


def _block(lanes: dict, idx: torch.Tensor, bins: ExitBins, compiled: bool):
    """The shard runner's exit lookup on a block of lanes."""
    from workers.walk.harvest import exit_function

    return exit_function(compiled)(idx, _as_lanes(lanes), bins)


@pytest.mark.slow
def test_compiled_exit_lookup_agrees_with_the_eager_one():
    """The compiled lookup gives the eager function's bins, batches and G exactly; S = w / cos_o
    to float64 rounding (inductor multiplies by reciprocals of constants and contracts to FMA)."""
    env = dict(os.environ, BSSRDF_COMPILE="1")
    root = Path(__file__).resolve().parents[2]
    proc = subprocess.run([sys.executable, "-c", _COMPILED_SCRIPT], cwd=root, env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-4000:]
    *same, s_rel = json.loads(proc.stdout.strip().splitlines()[-1])
    names = ["flat", "batch", "G", "S"]
    assert len(same) == len(names) and all(same[:3]), [n for n, ok in zip(names, same) if not ok]
    assert s_rel < 1e-14
