"""Tests of the bin geometry and lookup (workers/walk/binning.py) on hand-written layouts.

Areas and solid angles against their closed forms, equal-solid-angle directional bins by a
chi-square on isotropic directions, half-open [lo, hi) lookup at exact edges, angle wrapping,
and the outgoing azimuth measured from the radial direction (workers/walk/conventions.py, "Angles of a bin").
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from schema import azimuth_edges, uniform_edges
from tests.support.stats import assert_chi2
from tests.reference.binning import azimuth_edge_index, edge_index, searched
from workers.fold.configs import BinLayout
from workers.walk.binning import TWO_PI, _edge_function, azimuth_index, exact_divmod, outgoing_azimuth, uniform_index, wrap_angle

# Two channels with different radial edges (mm), same bin count.
RADIAL = np.array(
    [
        [0.0, 0.1, 0.25, 0.5, 1.0, 2.0],
        [0.0, 0.05, 0.2, 0.6, 1.5, 3.0],
    ]
)


def _layout(n_theta: int = 12, n_cos: int = 8, n_phi: int = 8, radial: np.ndarray = RADIAL) -> BinLayout:
    return BinLayout(
        radial_mm=radial,
        theta_s=azimuth_edges(n_theta),
        cos_o=np.linspace(0.0, 1.0, n_cos + 1),
        phi_o=azimuth_edges(n_phi),
    )


def test_shape_and_counts():
    lay = _layout(n_theta=12, n_cos=5, n_phi=7)
    assert (lay.n_r, lay.n_theta, lay.n_cos, lay.n_phi) == (5, 12, 5, 7)
    assert lay.shape == (6, 12, 5, 7)  # radial axis has the overflow bin


# --- areas and solid angles ------------------------------------------------------------------------


@pytest.mark.parametrize("n_theta", [1, 4, 12])
@pytest.mark.parametrize("channel", [0, 1])
def test_area_closed_form_and_full_disk(channel, n_theta):
    lay = _layout(n_theta=n_theta)
    area = lay.area_mm2(channel)
    assert area.shape == (lay.n_r, n_theta)
    r = RADIAL[channel]
    dtheta = TWO_PI / n_theta
    for i in range(lay.n_r):
        for j in range(n_theta):
            assert area[i, j] == pytest.approx((r[i + 1] ** 2 - r[i] ** 2) / 2.0 * dtheta, rel=1e-13)
    assert area.sum() == pytest.approx(math.pi * r[-1] ** 2, rel=1e-13)
    # Each full ring is pi (r_hi^2 - r_lo^2).
    np.testing.assert_allclose(area.sum(axis=1), math.pi * np.diff(r**2), rtol=1e-13)


@pytest.mark.parametrize("n_cos,n_phi", [(8, 8), (5, 7), (1, 1), (10, 36)])
def test_solid_angle_equal_and_sums_to_hemisphere(n_cos, n_phi):
    omega = _layout(n_cos=n_cos, n_phi=n_phi).solid_angle()
    assert omega.shape == (n_cos, n_phi)
    assert omega.sum() == pytest.approx(TWO_PI, rel=1e-13)
    np.testing.assert_allclose(omega, TWO_PI / (n_cos * n_phi), rtol=1e-12)


@pytest.mark.parametrize("n_cos,n_phi", [(8, 8), (5, 7)])
def test_isotropic_directions_fill_bins_equally(n_cos, n_phi):
    """Directions uniform on the hemisphere (normalised Gaussians, not drawn in (cos, phi)), with
    phi_o measured from the radial direction of random exit points, land in every directional
    bin with probability Omega / (2 pi): chi-square."""
    lay = _layout(n_cos=n_cos, n_phi=n_phi)
    rng = np.random.default_rng(21)
    n = 2**19
    v = rng.normal(size=(2 * n, 3))
    v = v[v[:, 2] > 0][:n]
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    p = rng.uniform(-2.0, 2.0, size=(len(v), 2))
    t = torch.from_numpy
    phi = outgoing_azimuth(t(p[:, 0]), t(p[:, 1]), t(v[:, 0]), t(v[:, 1]))
    ic = searched(lay).cos_index(t(v[:, 2]))
    ip = searched(lay).phi_index(phi)
    counts = np.bincount((ic * n_phi + ip).numpy(), minlength=n_cos * n_phi)
    masses = (lay.solid_angle() / TWO_PI).ravel()
    assert_chi2(counts, masses, len(v), n_tests=2, what=f"directional bins {n_cos}x{n_phi}")


# --- radial lookup ---------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
def test_radial_index_half_open_and_overflow(dtype):
    lay = _layout()
    n_r = lay.n_r
    for ch in (0, 1):
        edges = torch.as_tensor(RADIAL[ch], dtype=dtype)
        chan = torch.full((len(edges),), ch, dtype=torch.int64)
        # Exact edges go to the bin above: r = edge_k -> k; r_max -> overflow n_r.
        assert searched(lay).radial_index(edges, chan).tolist() == list(range(n_r + 1))
        # Just below an edge: the bin below.
        below = torch.nextafter(edges[1:], torch.zeros_like(edges[1:]))
        assert searched(lay).radial_index(below, chan[1:]).tolist() == list(range(n_r))
        mids = 0.5 * (edges[1:] + edges[:-1])
        assert searched(lay).radial_index(mids, chan[1:]).tolist() == list(range(n_r))
        beyond = torch.tensor([RADIAL[ch][-1] * 1.0001, 10.0 * RADIAL[ch][-1], 1e30], dtype=dtype)
        assert searched(lay).radial_index(beyond, torch.full((3,), ch)).tolist() == [n_r] * 3


def test_radial_index_per_channel_edges():
    """The same r in different channels follows that channel's edges."""
    lay = _layout()
    r = torch.tensor([0.07, 0.07, 0.55, 0.55, 2.5, 2.5, 0.1, 0.1, 0.2, 0.2], dtype=torch.float64)
    ch = torch.tensor([0, 1, 0, 1, 0, 1, 0, 1, 0, 1])
    want = []
    for ri, ci in zip(r.tolist(), ch.tolist()):
        e = RADIAL[ci]
        want.append(int(np.searchsorted(e, ri, side="right") - 1) if ri < e[-1] else lay.n_r)
    assert searched(lay).radial_index(r, ch).tolist() == want
    assert want == [0, 1, 3, 2, 5, 4, 1, 1, 1, 2]


def test_radial_index_batch_shape():
    lay = _layout()
    r = torch.tensor([[0.0, 0.3], [1.2, 5.0]], dtype=torch.float64)
    ch = torch.tensor([[0, 1], [1, 0]])
    assert searched(lay).radial_index(r, ch).tolist() == [[0, 2], [3, 5]]


# --- angular lookup --------------------------------------------------------------------------------

COUNTS = [1, 2, 3, 4, 5, 6, 8, 10, 12, 16, 24, 36]


@pytest.mark.parametrize("n", COUNTS)
def test_angle_indices_at_exact_edges(n):
    """Every bin is [lo, hi): the layout's own edge theta_k / phi_k is in bin k, 0 in the first
    (the bins are centred on 0)."""
    lay = _layout(n_theta=n, n_phi=n)
    for name, edges, index in (("theta_s", lay.theta_s, searched(lay).theta_index), ("phi_o", lay.phi_o, searched(lay).phi_index)):
        assert index(torch.tensor([0.0], dtype=torch.float64)).tolist() == [0]
        assert index(torch.tensor([0.0], dtype=torch.float32)).tolist() == [0]
        lo = torch.as_tensor(edges[:-1])
        got = index(lo).tolist()
        assert got == list(range(n)), f"{name} edges {edges[:-1].tolist()} -> bins {got} ({n} bins)"


@pytest.mark.parametrize("n", COUNTS)
def test_angle_indices_just_below_edges(n):
    """The largest float64 below the layout's edge theta_k / phi_k is in bin k - 1."""
    lay = _layout(n_theta=n, n_phi=n)
    for name, edges, index in (("theta_s", lay.theta_s, searched(lay).theta_index), ("phi_o", lay.phi_o, searched(lay).phi_index)):
        hi = torch.as_tensor(edges[1:-1])
        below = torch.nextafter(hi, torch.zeros_like(hi))
        got = index(below).tolist()
        assert got == list(range(n - 1)), f"{name}: one ulp below {edges[1:-1].tolist()} -> bins {got} ({n} bins)"
        assert index(torch.tensor([math.nextafter(edges[-1], 0.0)], dtype=torch.float64)).tolist() == [n - 1]
        # Just below 2 pi is just below 0: the first bin, which is centred on 0.
        assert index(torch.tensor([math.nextafter(TWO_PI, 0.0), -1e-12], dtype=torch.float64)).tolist() == [0, 0]


@pytest.mark.parametrize("n", COUNTS)
def test_cos_index_at_exact_edges(n):
    """cos = cos_k is in bin k, cos = 1 (straight up) in the last bin, cos = 0 in the first."""
    lay = _layout(n_cos=n)
    lo = torch.as_tensor(lay.cos_o[:-1])
    got = searched(lay).cos_index(lo).tolist()
    assert got == list(range(n)), f"cos edges {lay.cos_o[:-1].tolist()} -> bins {got}"
    assert searched(lay).cos_index(torch.tensor([0.0, 1.0])).tolist() == [0, n - 1]
    assert searched(lay).cos_index(torch.tensor([1.0], dtype=torch.float32)).tolist() == [n - 1]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("hi", [1.0, TWO_PI, 0.3, 7.0])
def test_computed_uniform_edges_are_the_stored_edges(hi, dtype):
    """The edges uniform_index computes from lo = 0 are bitwise those of schema.uniform_edges
    (numpy's linspace), for every count up to 400."""
    for count in range(1, 401):
        stored = torch.from_numpy(uniform_edges(0.0, hi, count)).to(dtype)
        computed = _edge_function(0.0, hi, count, dtype)(torch.arange(count + 1))
        assert torch.equal(computed, stored), (hi, count)


@pytest.mark.parametrize("lo,hi", [(0.0, 1.0), (0.0, TWO_PI), (-1.0, 2.5)])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
def test_uniform_index_is_the_edge_lookup(lo, hi, dtype):
    """uniform_index agrees with the searched lookup edge_index on the edges, one ulp either side
    of them and random values, for many counts."""
    gen = torch.Generator().manual_seed(3)
    for count in (1, 2, 3, 7, 8, 10, 36, 100):
        edges = torch.from_numpy(uniform_edges(lo, hi, count)).to(dtype)
        v = torch.cat((edges, torch.nextafter(edges, edges - 1), torch.nextafter(edges, edges + 1),
                       lo + (hi - lo) * torch.rand(2000, generator=gen, dtype=dtype)))  # fmt: skip
        assert torch.equal(uniform_index(v, lo, hi, count), edge_index(v, edges)), count


def test_uniform_index_interior_and_clamping():
    v = torch.tensor([-0.5, 0.0, 0.49, 0.5, 0.99, 1.0, 1.5], dtype=torch.float64)
    assert uniform_index(v, 0.0, 1.0, 2).tolist() == [0, 0, 0, 1, 1, 1, 1]
    assert uniform_index(v, 0.0, 1.0, 2).dtype == torch.int64


# --- azimuth bins centred on the plane of incidence -----------------------------------------------


@pytest.mark.parametrize("n", COUNTS)
def test_azimuth_edges_are_centred_on_zero(n):
    """Bin 0 is [-h/2, h/2), the edges span one turn from -h/2 in steps h = 2 pi / n, and the
    mirror image [-hi, -lo) of every bin is a bin of the layout: (n - k) mod n."""
    e = azimuth_edges(n)
    h = TWO_PI / n
    assert len(e) == n + 1 and e[0] == -h / 2 and e[-1] == pytest.approx(TWO_PI - h / 2, abs=1e-15)
    np.testing.assert_allclose(np.diff(e), h, rtol=1e-12)
    assert e[0] < 0.0 < e[1] and e[1] == pytest.approx(-e[0], rel=1e-15)
    centres = 0.5 * (e[:-1] + e[1:])
    for k in range(n):
        m = (n - k) % n
        # (mirror of bin k's centre) == bin m's centre, modulo 2 pi
        assert math.remainder(-centres[k] - centres[m], TWO_PI) == pytest.approx(0.0, abs=1e-12), (n, k)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("n", COUNTS)
def test_azimuth_index_is_the_searched_lookup(n, dtype):
    """azimuth_index agrees with the searched lookup on the stored edges (angle taken modulo
    2 pi) for random angles over several turns; on an edge and one ulp either side it may only
    differ by the rounding of the half-bin shift, i.e. give the neighbouring bin."""
    gen = torch.Generator().manual_seed(7)
    edges = torch.from_numpy(azimuth_edges(n))
    a = ((torch.rand(20_000, generator=gen, dtype=torch.float64) - 0.5) * 6 * TWO_PI).to(dtype)
    a = torch.cat((a, torch.tensor([0.0, -0.0, math.pi, -math.pi, TWO_PI], dtype=dtype)))
    got, want = azimuth_index(a, n), azimuth_edge_index(a, edges)
    assert got.dtype == torch.int64
    assert torch.equal(got, want), (n, a[got != want][:5].tolist())
    e = edges.to(dtype)
    near = torch.cat((e, torch.nextafter(e, e - 1), torch.nextafter(e, e + 1)))
    diff = (azimuth_index(near, n) - azimuth_edge_index(near, edges)) % n
    assert bool(((diff == 0) | (diff == 1) | (diff == n - 1)).all())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("n", COUNTS)
def test_azimuth_index_is_mirror_symmetric(n, dtype):
    """An angle a and its mirror -a land in bins k and (n - k) mod n; a = 0 (leaving radially,
    or straight ahead along +x) and a = pi land in bins that are their own mirror."""
    gen = torch.Generator().manual_seed(8)
    a = ((torch.rand(20_000, generator=gen, dtype=torch.float64) - 0.5) * 2 * TWO_PI).to(dtype)
    k, m = azimuth_index(a, n), azimuth_index(-a, n)
    edges = torch.from_numpy(azimuth_edges(n)).to(dtype)
    # Exclude angles within a few ulp of an edge (where half-open [lo, hi) breaks the tie).
    dist = torch.remainder(a.double()[:, None] - edges.double()[None, :], TWO_PI)
    clear = (torch.minimum(dist, TWO_PI - dist) > 1e-5).all(dim=1)
    assert clear.sum() > 19_000
    assert torch.equal(m[clear], (n - k[clear]) % n)
    zero = azimuth_index(torch.tensor([0.0, -1e-7, 1e-7, math.pi], dtype=dtype), n)
    assert zero[:3].tolist() == [0, 0, 0]
    if n % 2 == 0:  # pi (straight back) is the centre of bin n/2, its own mirror
        assert int(zero[3]) == n // 2


# --- wrapping --------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
def test_wrap_angle_cases(dtype):
    a = torch.tensor([-1e-7, TWO_PI, -math.pi / 2, 0.0, math.pi, 2 * TWO_PI + 0.25, -TWO_PI - 0.25], dtype=dtype)
    got = wrap_angle(a)
    assert got.dtype == dtype
    want = [0.0, 0.0, 1.5 * math.pi, 0.0, math.pi, 0.25, TWO_PI - 0.25]
    tol = 1e-12 if dtype == torch.float64 else 2e-6
    np.testing.assert_allclose(got.double().numpy(), want, rtol=0, atol=tol)
    assert float(got[0]) == 0.0 and float(got[1]) == 0.0  # exactly, so they land in the first bin
    lay = _layout(n_phi=8)
    assert searched(lay).phi_index(got[:2]).tolist() == [0, 0]
    assert searched(lay).phi_index(got[2:3]).tolist() == [6]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
def test_wrap_angle_range(dtype):
    a = torch.from_numpy(np.random.default_rng(22).uniform(-50.0, 50.0, 100_000)).to(dtype)
    w = wrap_angle(a)
    assert bool((w >= 0).all()) and bool((w < TWO_PI).all())
    # Same angle: cos and sin unchanged.
    tol = 1e-12 if dtype == torch.float64 else 2e-5
    np.testing.assert_allclose(torch.cos(w).double().numpy(), torch.cos(a).double().numpy(), atol=tol)
    np.testing.assert_allclose(torch.sin(w).double().numpy(), torch.sin(a).double().numpy(), atol=tol)


# --- outgoing azimuth ------------------------------------------------------------------------------

QUADRANT_DIRS = [(1.0, 0.0), (0.6, 0.8), (0.0, 1.0), (-0.8, 0.6), (-1.0, 0.0), (-0.6, -0.8), (0.0, -1.0), (0.8, -0.6)]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
def test_outgoing_azimuth_radial_is_zero(dtype):
    """Leaving radially outward gives phi_o = 0 exactly, wherever the exit point is, including
    positions built as x = s * u_x, y = s * u_y from the direction itself (float32 products that
    are parallel up to rounding)."""
    rng = np.random.default_rng(23)
    ang = np.concatenate([np.arctan2([d[1] for d in QUADRANT_DIRS], [d[0] for d in QUADRANT_DIRS]),
                          rng.uniform(0, TWO_PI, 2000)])
    tx = torch.from_numpy(np.cos(ang)).to(dtype)
    ty = torch.from_numpy(np.sin(ang)).to(dtype)
    for s in (1e-6, 0.37, 1.0, 3.1, 250.0):
        px, py = s * tx, s * ty  # rounded in dtype
        phi = outgoing_azimuth(px, py, tx, ty)
        assert phi.dtype == dtype
        # Zero up to rounding of the cross product, and never wrapped to just below 2 pi.
        tol = 1e-12 if dtype == torch.float64 else 1e-6
        bad = torch.nonzero((phi < 0.0) | (phi > tol)).flatten()
        assert bad.numel() == 0, f"phi_o = {phi[bad[:3]].tolist()} for radial exits at s = {s}"
        lay = _layout(n_phi=8)
        assert bool((searched(lay).phi_index(phi) == 0).all())


def test_outgoing_azimuth_at_origin_measures_from_x():
    z = torch.zeros(4, dtype=torch.float64)
    tx = torch.tensor([1.0, 0.0, -1.0, 0.0], dtype=torch.float64)
    ty = torch.tensor([0.0, 1.0, 0.0, -1.0], dtype=torch.float64)
    np.testing.assert_allclose(outgoing_azimuth(z, z, tx, ty).numpy(), [0.0, math.pi / 2, math.pi, 1.5 * math.pi],
                               atol=1e-15)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
def test_outgoing_azimuth_counterclockwise(dtype):
    """A direction rotated by +alpha (counterclockwise seen from +z) from the outward radial
    direction has phi_o = alpha; +90 deg gives pi/2 in every quadrant."""
    rng = np.random.default_rng(24)
    tol = 1e-12 if dtype == torch.float64 else 2e-6
    for dx, dy in QUADRANT_DIRS:
        px = torch.tensor([2.0 * dx], dtype=dtype)
        py = torch.tensor([2.0 * dy], dtype=dtype)
        phi = outgoing_azimuth(px, py, torch.tensor([-dy], dtype=dtype), torch.tensor([dx], dtype=dtype))
        assert float(phi) == pytest.approx(math.pi / 2, abs=tol)
    n = 5000
    beta = rng.uniform(0, TWO_PI, n)  # position angle
    alpha = rng.uniform(0, TWO_PI, n)  # rotation from radial
    r = rng.uniform(0.01, 5.0, n)
    t = lambda a: torch.from_numpy(a).to(dtype)  # noqa: E731
    phi = outgoing_azimuth(t(r * np.cos(beta)), t(r * np.sin(beta)), t(np.cos(beta + alpha)), t(np.sin(beta + alpha)))
    diff = np.angle(np.exp(1j * (phi.double().numpy() - alpha)))  # wrapped difference
    np.testing.assert_allclose(diff, 0.0, atol=tol * 10)
    assert bool((phi >= 0).all()) and bool((phi < TWO_PI).all())


def _divmod_cases() -> tuple[list[int], list[torch.Tensor]]:
    """Divisors from 1 to 2**40, and for each, dividends at and beside its multiples from 0 up
    to just below 2**50 (where the quotient's rounding comes closest to an integer)."""
    divisors = [1, 2, 3, 7, 12, 64, 100, 1000, 4097, 2**20 + 7, 2**30 - 1, 2**40 + 1]
    rows = []
    for n in divisors:
        top = (2**50 - 1) // n
        k = torch.cat((torch.arange(0, 2000), torch.randint(0, top, (4000,), generator=torch.Generator().manual_seed(n)), torch.arange(top - 2000, top)))
        a = (k[:, None] * n + torch.tensor([-1, 0, 1])).reshape(-1)
        rows.append(a[(a >= 0) & (a < 2**50)])
    return divisors, rows


def test_exact_divmod_is_integer_division():
    """exact_divmod (float64, so that compiled kernels divide in vectors) equals int64 // and %
    beside every kind of multiple, with the divisor an int or a 0-d tensor (as the harvest
    passes it)."""
    for n, a in zip(*_divmod_cases()):
        for divisor in (n, torch.tensor(n)):
            q, r = exact_divmod(a, divisor)
            assert q.dtype == torch.int64 and r.dtype == torch.int64
            assert torch.equal(q, a // n) and torch.equal(r, a % n), n


def test_exact_divmod_compiled():
    """The same through inductor, whose generated code rounds on its own: the divisor baked in as
    a constant (the hybrid's theta_s count) and as a tensor (the harvest's configuration count)."""
    divisors, rows = _divmod_cases()
    by_tensor = torch.compile(exact_divmod, dynamic=True, fullgraph=True)
    for n, a in zip(divisors, rows):
        assert all(torch.equal(x, y) for x, y in zip(by_tensor(a, torch.tensor(n)), (a // n, a % n))), n
    picked = list(zip(divisors, rows))[2::3]  # every divisor baked into one graph: one compile
    baked = torch.compile(lambda rows: [exact_divmod(a, n) for (n, _), a in zip(picked, rows)], fullgraph=True)
    for (n, a), (q, r) in zip(picked, baked([a for _, a in picked])):
        assert torch.equal(q, a // n) and torch.equal(r, a % n), n
