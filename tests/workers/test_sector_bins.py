"""Azimuth bins of a direction decided without its angle (workers/walk/binning.py:
sector_index, outgoing_azimuth_index): against the searched lookup of the exact angle on the
stored edges, at and near every edge, for the zero vector and the axes, under mirroring, and
compiled against eager."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from schema import azimuth_edges
from tests.reference.binning import azimuth_edge_index
from workers.walk.binning import SECTOR_MAX, TWO_PI, azimuth_index, outgoing_azimuth, outgoing_azimuth_index, sector_index

SECTOR_COUNTS = [1, 2, 3, 4, 5, 6, 8, 10, 12, 16, 17, 24, 36, 60, 360]  # beyond SECTOR_MAX (16): the atan2 lookup
# How close to an edge (rad) the rounding of one cross product may move a direction's bin.
SECTOR_TOL = {torch.float64: 1e-12, torch.float32: 1e-6}


def _edge_distance(angle: np.ndarray, n: int) -> np.ndarray:
    """Distance (rad) of each angle to the nearest azimuth bin edge among n."""
    d = np.remainder(angle[:, None] - azimuth_edges(n)[None, :], TWO_PI)
    return np.minimum(d, TWO_PI - d).min(axis=1)


def _exact_bin(x: torch.Tensor, y: torch.Tensor, n: int) -> tuple[torch.Tensor, np.ndarray]:
    """(bin, angle): the searched lookup of the angle of the stored vector (x, y), taken in
    float64 (for float32 vectors: exact to ~1e-16 rad), on the stored edges."""
    angle = np.arctan2(y.double().numpy(), x.double().numpy())
    return azimuth_edge_index(torch.from_numpy(angle), torch.from_numpy(azimuth_edges(n))), angle


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("n", SECTOR_COUNTS)
def test_sector_index_is_the_lookup_of_the_exact_angle(n, dtype):
    """sector_index(y, x, n) is the bin of the angle of (x, y) on the stored edges: for random
    directions of lengths 1e-20 .. 1e20, for directions 10 tolerances either side of every edge
    (the cross products must tell them apart), and within the tolerance of an edge at most the
    neighbouring bin."""
    gen = np.random.default_rng(41)
    m = 20_000
    a, length = gen.uniform(-6 * TWO_PI, 6 * TWO_PI, m), 10.0 ** gen.uniform(-20, 20, m)
    edges = azimuth_edges(n)
    tol = SECTOR_TOL[dtype]
    near = np.concatenate([edges - 10 * tol, edges + 10 * tol])
    a = np.concatenate([a, near, near + TWO_PI])
    length = np.concatenate([length, np.ones(2 * len(near))])
    x = torch.from_numpy(length * np.cos(a)).to(dtype)
    y = torch.from_numpy(length * np.sin(a)).to(dtype)
    got = sector_index(y, x, n)
    want, angle = _exact_bin(x, y, n)
    assert got.dtype == torch.int64
    clear = torch.from_numpy(_edge_distance(angle, n) > tol)
    assert int(clear.sum()) > 0.99 * len(a)
    assert torch.equal(got[clear], want[clear]), (n, angle[~(got == want).numpy() & clear.numpy()][:5])
    diff = (got - want) % n
    assert bool(((diff == 0) | (diff == 1) | (diff == n - 1)).all())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("n", SECTOR_COUNTS)
def test_sector_index_axes_zero_and_mirror(n, dtype):
    """The zero vector (any signs) is in bin 0, as is +x; -x is in bin n/2 for even n (the
    centre of that bin); a direction and its mirror (x, -y) clear of the edges land in bins k
    and (n - k) mod n."""
    zero = torch.tensor([0.0, -0.0, 0.0, -0.0], dtype=dtype)
    assert sector_index(zero, zero.flip(0), n).tolist() == [0, 0, 0, 0]
    one = torch.tensor([1.0, 1e-30, 3.5], dtype=dtype)
    assert sector_index(torch.zeros_like(one), one, n).tolist() == [0, 0, 0]
    assert sector_index(-torch.zeros_like(one), one, n).tolist() == [0, 0, 0]
    if n % 2 == 0:
        assert sector_index(torch.zeros_like(one), -one, n).tolist() == [n // 2] * 3
    if 1 < n <= SECTOR_MAX and dtype == torch.float64:
        # Half-open: the direction of edge j, as the kernel's constants (cos, sin), is in bin j.
        # Not the edge at pi (odd n): its rounded direction (-1, 1.2e-16) lies just short of pi.
        h = TWO_PI / n
        js = [j for j in range(1, n + 1) if 2 * j - 1 != n]
        x = torch.tensor([math.cos((j - 0.5) * h) for j in js], dtype=dtype)
        y = torch.tensor([math.sin((j - 0.5) * h) for j in js], dtype=dtype)
        assert sector_index(y, x, n).tolist() == [j % n for j in js]
    gen = np.random.default_rng(42)
    a = gen.uniform(0, TWO_PI, 20_000)
    a = a[_edge_distance(a, n) > 1e-5]
    x, y = (torch.from_numpy(f(a)).to(dtype) for f in (np.cos, np.sin))
    assert torch.equal(sector_index(-y, x, n), (n - sector_index(y, x, n)) % n)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("n", [1, 4, 8, 12, 16, 24])
def test_outgoing_azimuth_index_is_the_bin_of_phi_o(n, dtype):
    """outgoing_azimuth_index is the bin of outgoing_azimuth (clear of the edges by more than the
    rounding of the two), radial exits (position built from the direction) are in bin 0, at the
    origin phi_o is measured from +x, and a direction with no horizontal part is in bin 0."""
    gen = np.random.default_rng(43)
    m = 20_000
    beta, alpha, r = gen.uniform(0, TWO_PI, m), gen.uniform(0, TWO_PI, m), gen.uniform(0.01, 5.0, m)
    t = lambda v: torch.from_numpy(v).to(dtype)  # noqa: E731
    px, py, tx, ty = t(r * np.cos(beta)), t(r * np.sin(beta)), t(np.cos(beta + alpha)), t(np.sin(beta + alpha))
    got = outgoing_azimuth_index(px, py, tx, ty, n)
    phi = outgoing_azimuth(px, py, tx, ty)
    clear = torch.from_numpy(_edge_distance(phi.double().numpy(), n) > 1e-5)
    assert int(clear.sum()) > 0.99 * m
    assert torch.equal(got[clear], azimuth_index(phi, n)[clear])
    # Radial exits, their positions rounded in dtype from the direction: bin 0.
    s = t(gen.uniform(1e-6, 250.0, m))
    assert bool((outgoing_azimuth_index(s * tx, s * ty, tx, ty, n) == 0).all())
    # At the origin: measured from +x.
    z = torch.zeros(4, dtype=dtype)
    quarter = outgoing_azimuth_index(z, z, t(np.array([1.0, 0.0, -1.0, 0.0])), t(np.array([0.0, 1.0, 0.0, -1.0])), n)
    axes = np.array([0.0, 0.5, 1.0, 1.5]) * math.pi
    clear = torch.from_numpy(_edge_distance(axes, n) > 1e-9)  # n = 2 mod 4 has edges on the y axis
    assert torch.equal(quarter[clear], azimuth_index(torch.from_numpy(axes), n)[clear])
    # Straight up (no horizontal part, either sign of zero): bin 0, wherever it leaves.
    for zx, zy in ((0.0, 0.0), (-0.0, 0.0), (0.0, -0.0), (-0.0, -0.0)):
        assert bool((outgoing_azimuth_index(px[:50], py[:50], torch.full((50,), zx, dtype=dtype), torch.full((50,), zy, dtype=dtype), n) == 0).all())


def test_sector_index_compiled_is_eager():
    """The compiled kernels decide the bins as the eager code does (clear of the edges; the
    compiler may fuse a cross product's multiply and subtract)."""
    from workers.walk.kernels import compile_kernel

    def bins(y, x):
        return tuple(sector_index(y, x, n) for n in (1, 2, 3, 8, 12, SECTOR_MAX, SECTOR_MAX + 1))

    gen = np.random.default_rng(44)
    a = gen.uniform(0, TWO_PI, 4096)
    for dtype in (torch.float64, torch.float32):
        x, y = (torch.from_numpy(f(a)).to(dtype) for f in (np.cos, np.sin))
        for n, c, e in zip((1, 2, 3, 8, 12, SECTOR_MAX, SECTOR_MAX + 1), compile_kernel(bins, f"test_sector_{dtype}")(y, x), bins(y, x)):
            clear = torch.from_numpy(_edge_distance(a, n) > 1e-5)
            assert torch.equal(c[clear], e[clear]), n
