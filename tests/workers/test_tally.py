"""Per-photon second moments (workers.fold.tally): several contributions of one photon to one entry
are squared together, in the numpy reference and in the hybrid's fused kernel alike."""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import torch

from workers.walk.hybrid import photon_entries
from workers.run.plan import ShardPlan
from workers.run.shard import _Runner, ordered_sum as torch_ordered_sum
from workers.fold.tally import RD_SQUARE_ROWS, PhotonAccumulator, TallyLayout, entry_square_keys, fold_square_totals, ordered_sum, photon_moments
from workers.walk.walk import EMPTY, RUNNING


def _brute_squares(key: np.ndarray, value: np.ndarray, size: int) -> np.ndarray:
    """sum over photons of (photon's sum per key)^2, by a dictionary per photon."""
    out = np.zeros(size)
    for ks, vs in zip(key.reshape(-1, key.shape[-1]), value.reshape(-1, value.shape[-1])):
        per = defaultdict(float)
        for k, v in zip(ks, vs):
            per[int(k)] += float(v)
        for k, v in per.items():
            out[k] += v * v
    return out


def test_photon_moments_square_each_photons_sum_per_entry():
    rng = np.random.default_rng(3)
    key = rng.integers(0, 6, size=(2, 50, 5))  # few keys: many repeats within a photon
    value = rng.normal(size=key.shape) * (rng.random(key.shape) < 0.8)
    np.testing.assert_allclose(photon_moments(key, value, 6), _brute_squares(key, value, 6), rtol=1e-12, atol=1e-12)
    # One entry per photon: plain squares.
    np.testing.assert_allclose(photon_moments(key[..., :1], value[..., :1], 6), np.bincount(key[..., 0].ravel(), value[..., 0].ravel() ** 2, 6))


def test_hybrid_kernel_squares_per_photon(walk_spec):
    """photon_entries' compact squares, summed per key and completed by fold_square_totals, are
    the brute-force per-photon squares of its own entries, for every level and component
    (finished photons of a real eager walk)."""
    spec = walk_spec(0.1, 0.9, g=0.5, eta=1.3, n_r=3, max_mm=3.0, n_theta=2, n_cos=2, n_phi=2, incidence_deg=[30.0],
                     photons=300, shards=1, batches_per_shard=2, estimator="hybrid", seed=4)  # fmt: skip
    plan = ShardPlan.build(spec, 0)
    runner = _Runner(plan, None)
    with torch.no_grad():
        runner.fill()
        for _ in range(6):
            for chunk in runner.chunks:
                runner.kernels.step(chunk)
        st = runner.lanes.status
        idx = torch.nonzero((st != RUNNING) & (st != EMPTY)).squeeze(1)
        assert len(idx) > 50
        flat2, g, s, key, weight = (v.numpy() for v in photon_entries(idx, runner.lanes, plan.exit_bins, plan.first_vertex, plan.entry_layout))
    layout = runner.photons.layout
    size = int(layout.square_offsets[-1])
    assert key.shape == weight.shape == (3 * (g.shape[1] + 1) + 3, len(idx))  # 18 values a photon at E = 4, not 8 E
    values = np.stack([g, s, g, g, g, s, g, g])
    want = _brute_squares(entry_square_keys(flat2, layout), values, size)
    # A photon's entries share keys: several samples in one bin, and the exit with samples at the total level.
    assert (want > 0).sum() > 20
    got = fold_square_totals(np.bincount(key.reshape(-1), weights=weight.reshape(-1), minlength=size), layout)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-300)
    acc = PhotonAccumulator(["hybrid"], plan.cfgs.n, plan.layout.shape)  # the accumulator folds each block alike
    acc.add_photons("hybrid", flat2, g, s, key, weight)
    acc.add_photons("hybrid", flat2, g, s, key, weight)
    np.testing.assert_allclose(acc.squares["hybrid"], 2.0 * want, rtol=1e-12, atol=1e-300)
    assert np.all(g[:, :-1] >= 0) and (g[:, :-1] > 0).any() and flat2.shape == g.shape
    # The phase sample's zeros (it pointed down) are spread over bins, not chained in one (photon_entries).
    down = (g[:, -2] == 0) & (s[:, -2] == 0)
    assert down.sum() > 20 and len(np.unique(flat2[down, -2])) > 20


def test_entry_square_keys_index_each_level_and_component_of_the_entry():
    """entry_square_keys against the histograms' own shapes: the key of an entry is its
    [cfg, component or total, spatial (ring), direction] cell, offset into its region."""
    layout = TallyLayout(n_cfg=2, hist_shape=(4, 3, 2, 5))  # n_r + 1 = 4 rings, 3 theta_s, 2 x 5 directions
    rng = np.random.default_rng(8)
    cfg, comp = rng.integers(0, 2, size=(30, 4)), rng.integers(0, 2, size=(30, 4))
    ring, theta, cos, phi = (rng.integers(0, n, size=(30, 4)) for n in (4, 3, 2, 5))
    flat2 = np.ravel_multi_index((cfg, comp, ring, theta, cos, phi), (2, 2, 4, 3, 2, 5))
    keys = entry_square_keys(flat2, layout)
    o = layout.square_offsets
    for half, c in ((0, comp), (1, np.full_like(comp, 2))):
        bins = np.ravel_multi_index((cfg, c, ring, theta, cos, phi), (2, 3, 4, 3, 2, 5))
        np.testing.assert_array_equal(keys[4 * half + 0], o[0] + bins)
        np.testing.assert_array_equal(keys[4 * half + 1], o[1] + bins)
        np.testing.assert_array_equal(keys[4 * half + 2], o[2] + np.ravel_multi_index((cfg, c, ring), (2, 3, 4)))
        np.testing.assert_array_equal(keys[4 * half + 3], o[3] + np.ravel_multi_index((cfg, c), (2, 3)))
    assert o[4] == 2 * 2 * 3 * 4 * 3 * 10 + 2 * 3 * 4 + 2 * 3


def test_zero_weight_exits_are_no_events():
    """An exit of weight 0 (at albedo 0 a weight of 0 can survive roulette and leave) adds no
    event: the bin it alone reached stays unresolved, 0 with a NaN error, never 0 +- 0."""
    acc = PhotonAccumulator(["exits"], n_cfg=1, hist_shape=(2, 1, 1, 1))  # radial bins: one inside, one beyond r_max
    flat = np.array([0, 0, 1])  # [cfg 0, single, spatial bin 0/1, direction 0]
    acc.add_exits("exits", flat, np.array([0.5, 0.25, 0.0]), np.array([1.0, 0.5, 0.0]))
    _stats, counts = acc.finish(3)
    np.testing.assert_array_equal(counts["exits/bins_G"][0, 0, :, 0, 0, 0], [2, 0])
    np.testing.assert_array_equal(counts["exits/radial_G"][0, 2], [2, 0])  # total
    assert counts["exits/Rd"][0, 0] == 2


def _bits(a) -> np.ndarray:
    return np.asarray(a, dtype=np.float64).view(np.int64)


def test_ordered_sums_have_the_bits_of_a_bincount_into_one_bin():
    """Both sequential sums, numpy's (the fold's default) and torch's (the shard's), give the bits
    np.bincount gives a bin that receives every value: for values whose sum rounds differently
    in any other order (pairwise, as np.sum, is checked to differ), and for the edge cases."""
    rng = np.random.default_rng(11)
    one_bin = lambda v: np.bincount(np.zeros(v.size, dtype=np.int64), weights=v, minlength=1)[0]  # noqa: E731
    cases = [np.array([]), np.array([-0.0]), np.array([-0.0, -0.0]), np.array([-0.0, 0.0]), np.array([5e-324, -0.0, 5e-324]),
             np.array([1.0, np.inf]), np.array([np.inf, -np.inf])]  # fmt: skip
    for n in (1, 2, 7, 8, 9, 63, 64, 65, 4096, 10007):
        v = rng.standard_normal(n) * 10.0 ** rng.integers(-12, 12, n)
        v[rng.random(n) < 0.3] = 0.0
        cases.append(v)
    differs = 0
    for v in cases:
        with np.errstate(invalid="ignore"):  # inf - inf
            want = one_bin(v)
            got_all = [fn(v) for fn in (ordered_sum, torch_ordered_sum)]
        for fn, got in zip((ordered_sum, torch_ordered_sum), got_all):
            assert _bits(got) == _bits(want) or (np.isnan(got) and np.isnan(want)), (fn.__module__, v[:4], got, want)
        differs += v.size > 1000 and np.sum(v) != want
    assert differs  # the cases would catch a sum in another order


def test_one_configuration_sums_keep_the_bits_of_bincounts():
    """With one configuration the walk totals and Rd's squares are summed in order apart from the
    bincounts (PhotonAccumulator's docstring): every array the accumulator keeps has the bits
    of plain bincounts over the same inputs in the same order."""
    rng = np.random.default_rng(12)
    hist = (5, 2, 2, 3)
    layout = TallyLayout(1, hist)
    size, size2 = int(layout.square_offsets[-1]), 2 * layout.n_sp * layout.n_dir
    o_rd = int(layout.square_offsets[3])
    for fn in (ordered_sum, torch_ordered_sum):
        acc = PhotonAccumulator(["hybrid"], 1, hist, ordered_sum=fn)
        want_sq, want_walk = np.zeros(size), np.zeros((2, 3, 1))
        for p in (1, 3, 700, 4096):
            flat2 = rng.integers(0, size2, (p, 4))
            g = rng.random((p, 4)) * 10.0 ** rng.integers(-8, 8, (p, 4)) * (rng.random((p, 4)) < 0.7)
            s = g / rng.random((p, 4))
            q = 3 * 5 + RD_SQUARE_ROWS
            key = rng.integers(0, o_rd, (q, p))
            key[-RD_SQUARE_ROWS:] = o_rd + np.arange(RD_SQUARE_ROWS)[:, None]  # Rd's rows: the configuration's bin of each component
            weight = rng.random((q, p)) * 10.0 ** rng.integers(-8, 8, (q, p)) * (rng.random((q, p)) < 0.6)
            acc.add_photons("hybrid", flat2, g, s, key, weight)
            want_sq += fold_square_totals(np.bincount(key.ravel(), weights=weight.ravel(), minlength=size), layout)
            absorbed = rng.random(p) * 10.0 ** rng.integers(-8, 8, p) * (rng.random(p) < 0.5)
            truncated = np.where(rng.random(p) < 0.01, rng.random(p), 0.0)
            acc.add_walk(np.zeros(p, dtype=np.int64), absorbed, truncated)
            for i, v in enumerate((absorbed, truncated)):
                if (v != 0).any():
                    want_walk[i] += [np.bincount(np.zeros(p, dtype=np.int64), weights=w, minlength=1) for w in (v, v * v)] + [[np.count_nonzero(v)]]
        np.testing.assert_array_equal(_bits(acc.squares["hybrid"]), _bits(want_sq))
        np.testing.assert_array_equal(_bits(acc.walk["absorbed"]), _bits(want_walk[0]))
        np.testing.assert_array_equal(_bits(acc.walk["truncated"]), _bits(want_walk[1]))
        assert acc.walk["truncated"][2, 0] > 0 and np.count_nonzero(acc.squares["hybrid"][o_rd:]) == RD_SQUARE_ROWS
