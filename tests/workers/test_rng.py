"""Tests of the counter-based generator (workers/walk/rng.py).

Known-answer vectors of Philox-4x32-10 from Random123 (kat_vectors), the tensor version against
the plain-Python one, the float mappings, and statistical checks of uniformity and independence
across output words, neighbouring counters and neighbouring keys.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.support.stats import assert_chi2, assert_z, z_threshold
from workers.walk import rng
from workers.walk.rng import philox4x32, philox4x32_scalar, stream_key, to_i32, to_u32, uniform_halfopen, uniform_open

M32 = 0xFFFFFFFF

# Random123 kat_vectors, philox4x32 with 10 rounds: (counter, key, expected output).
KAT = [
    ((0, 0, 0, 0), (0, 0), (0x6627E8D5, 0xE169C58D, 0xBC57AC4C, 0x9B00DBD8)),
    ((M32, M32, M32, M32), (M32, M32), (0x408F276D, 0x41C83B0E, 0xA20BC7C6, 0x6D5451FD)),
    (
        (0x243F6A88, 0x85A308D3, 0x13198A2E, 0x03707344),
        (0xA4093822, 0x299F31D0),
        (0xD16CFE09, 0x94FDCCEB, 0x5001E420, 0x24126EA1),
    ),
]

# Statistical tests in this module, for the Sidak correction (tests.support.stats).
N_CHI2 = 4 + 4 + 3 + 1  # per-word uniformity, word pairs in a block, neighbour pairs, key pairs
N_Z = 4 * 32 + 6 + 4 + 1  # bit balance, word correlations, neighbour correlations, key correlation
Z_SIGMA = z_threshold(N_Z)  # ~4.96


def _tensors(counters, keys):
    """int64 column tensors (c0..c3, k0, k1) from lists of counters and keys."""
    c = torch.tensor(counters, dtype=torch.int64)
    k = torch.tensor(keys, dtype=torch.int64)
    return c[:, 0], c[:, 1], c[:, 2], c[:, 3], k[:, 0], k[:, 1]


def _block(n: int, key: tuple[int, int], c1: int = 0, c2: int = 0, c3: int = 0, start: int = 0):
    """Philox outputs (4 int64 tensors) for counters (start + i, c1, c2, c3), i < n."""
    c0 = torch.arange(start, start + n, dtype=torch.int64)
    z = torch.zeros_like(c0)
    return philox4x32(c0, z + c1, z + c2, z + c3, torch.tensor(key[0]), torch.tensor(key[1]))


KEY = stream_key(20240917, "tests.rng")


# --- known answers -------------------------------------------------------------------------------


@pytest.mark.parametrize("counter,key,expected", KAT)
def test_scalar_known_answers(counter, key, expected):
    assert philox4x32_scalar(counter, key) == expected


def test_tensor_known_answers_eager():
    counters, keys, expected = zip(*KAT)
    out = philox4x32(*_tensors(counters, keys))
    got = list(zip(*(w.tolist() for w in out)))
    assert got == list(expected)
    assert all(w.dtype == torch.int64 for w in out)


@pytest.mark.parametrize("wide", [False, True], ids=["int32-rounds", "int64-rounds"])
@pytest.mark.parametrize("n_rep", [11, 256])
def test_tensor_known_answers_compiled(n_rep, wide, monkeypatch):
    """Both compiled arithmetic forms (int32 lanes with 16-bit partial products; int64 where the
    ISA multiplies int64 vectors, see native_wide_multiply) must keep every 32-bit wrap-around
    through inductor code generation, in a scalar loop (33 elements) and a vectorized one (768)."""
    monkeypatch.setattr(rng, "_native_wide", wide)
    torch._dynamo.reset()
    compiled = torch.compile(philox4x32, dynamic=False, fullgraph=True)
    counters, keys, expected = zip(*KAT)
    cols = [to_i32(c) for c in _tensors(list(counters) * n_rep, list(keys) * n_rep)]
    out = compiled(*cols)
    assert all(w.dtype == torch.int32 for w in out)
    got = list(zip(*(to_u32(w).tolist() for w in out)))
    assert got == list(expected) * n_rep


def test_compiled_int64_words_are_refused():
    """int64 words inside a compiled graph could lose the 32-bit wrap: refused with a clear error."""
    compiled = torch.compile(philox4x32, dynamic=False, fullgraph=True)
    with pytest.raises(Exception, match="int32 words"):
        compiled(*_tensors([KAT[0][0]] * 8, [KAT[0][1]] * 8))


def test_int32_and_int64_rounds_agree_eager():
    """The two implementations of the rounds (int32 lanes for compiled code, int64 eager)."""
    from workers.walk.rng import _philox_i32, _philox_u64

    rng = np.random.default_rng(6)
    words = torch.from_numpy(rng.integers(0, 2**32, size=(6, 5000), dtype=np.uint64).astype(np.int64))
    words[:, :8] = M32
    words[:, 8:16] = 0
    for a, b in zip(_philox_u64(*words), _philox_i32(*(to_i32(w) for w in words))):
        assert torch.equal(a, to_u32(b))


def test_int32_and_int64_forms_agree():
    rng = np.random.default_rng(5)
    words = torch.from_numpy(rng.integers(0, 2**32, size=(6, 1000), dtype=np.uint64).astype(np.int64))
    wide = philox4x32(*words)
    narrow = philox4x32(*(to_i32(w) for w in words))
    for a, b in zip(wide, narrow):
        assert b.dtype == torch.int32
        assert torch.equal(a, to_u32(b))


def test_tensor_known_answers_broadcast_key():
    """Keys given as 0-d tensors broadcast over a batch of counters (as the walk calls it)."""
    for counter, key, expected in KAT:
        c = torch.tensor([counter] * 3, dtype=torch.int64)
        out = philox4x32(c[:, 0], c[:, 1], c[:, 2], c[:, 3], torch.tensor(key[0]), torch.tensor(key[1]))
        for w, e in zip(out, expected):
            assert w.tolist() == [e] * 3


def test_tensor_matches_scalar_on_random_inputs():
    rng = np.random.default_rng(1)
    n = 10_000
    counters = rng.integers(0, 2**32, size=(n, 4), dtype=np.uint64).astype(np.int64)
    keys = rng.integers(0, 2**32, size=(n, 2), dtype=np.uint64).astype(np.int64)
    # Extreme words: products near 2**64 exercise the signed wrap in _mulhilo.
    counters[:16] = M32
    counters[16:32] = 0
    keys[:8] = M32
    out = torch.stack(philox4x32(*_tensors(counters.tolist(), keys.tolist())), dim=1).tolist()
    for i in range(n):
        ref = philox4x32_scalar(tuple(int(v) for v in counters[i]), tuple(int(v) for v in keys[i]))
        assert tuple(out[i]) == ref, f"counter {counters[i].tolist()} key {keys[i].tolist()}"


def test_outputs_are_32_bit_and_inputs_unchanged():
    c0 = torch.tensor([M32, 0, 12345], dtype=torch.int64)
    before = c0.clone()
    out = philox4x32(c0, c0, c0, c0, torch.tensor(M32), torch.tensor(7))
    assert torch.equal(c0, before)
    for w in out:
        assert int(w.min()) >= 0 and int(w.max()) <= M32


# --- mapping to floats ---------------------------------------------------------------------------


def test_uniform_open_is_strictly_inside_unit_interval():
    """Every one of the 2**24 distinct values of x >> 8 maps into (0, 1), including the top one.

    ((x >> 8) + 0.5) / 2**24 is not representable in float32 once x >> 8 >= 2**23, and the
    top value 2**24 - 0.5 rounds to 2**24, i.e. u = 1.0 exactly (then log(1 - u) = -inf).
    """
    x = (torch.arange(2**24, dtype=torch.int64) << 8) | 0xFF  # the low 8 bits are discarded
    u = uniform_open(x)
    assert u.dtype == torch.float32
    bad = torch.nonzero((u <= 0.0) | (u >= 1.0)).flatten()
    assert bad.numel() == 0, (
        f"uniform_open returned {u[bad[:3]].tolist()} for x = {[hex(int(v)) for v in x[bad[:3]]]}"
    )
    assert torch.isfinite(torch.log(1.0 - u)).all() and torch.isfinite(torch.log(u)).all()


def test_uniform_open_extremes():
    # 23-bit grid offset by half a step: the 9 low bits are dropped, the extremes are 2**-24
    # and 1 - 2**-24, both exact in float32.
    x = torch.tensor([0, 0x1FF, M32], dtype=torch.int64)
    u = uniform_open(x)
    assert u[0] == u[1] == 0.5 / 2**23
    assert float(u[2]) == 1.0 - 2.0**-24
    assert 0.0 < float(u[2]) < 1.0, f"uniform_open(0xFFFFFFFF) = {float(u[2])!r}"


def test_uniform_halfopen_range_and_exact_grid():
    x = torch.arange(2**24, dtype=torch.int64) << 8
    u = uniform_halfopen(x | 0xFF)
    assert u.dtype == torch.float32
    assert float(u.min()) == 0.0 and float(u.max()) == 1.0 - 2.0**-24
    # Exact 24-bit grid: k / 2**24 for every k, so all 2**24 values are distinct and in order.
    assert torch.equal(u.double() * 2**24, torch.arange(2**24, dtype=torch.float64))


# --- statistics ----------------------------------------------------------------------------------

N_STAT = 2**20  # draws per output word


@pytest.fixture(scope="module")
def words():
    """4 x 2**20 uniforms in [0, 1) (float64) from consecutive counters of one key."""
    out = _block(N_STAT, KEY, c2=5)
    return [uniform_halfopen(w).double().numpy() for w in out]


@pytest.mark.parametrize("word", range(4))
def test_uniformity_chi2(words, word):
    cells = 256
    counts = np.bincount((words[word] * cells).astype(np.int64), minlength=cells)
    assert_chi2(counts, np.full(cells, 1.0 / cells), N_STAT, n_tests=N_CHI2, what=f"word {word}")


def test_uniform_open_uniformity_chi2():
    """uniform_open over 2**20 draws, 256 cells (the half-step offset must not skew cells)."""
    u = uniform_open(_block(N_STAT, KEY, c3=3)[0]).double().numpy()
    cells = 256
    counts = np.bincount((u * cells).astype(np.int64).clip(0, cells - 1), minlength=cells)
    assert_chi2(counts, np.full(cells, 1.0 / cells), N_STAT, n_tests=N_CHI2, what="uniform_open")


def test_bits_are_balanced():
    """Each of the 32 bits of each word is 1 with probability 1/2."""
    n = N_STAT // 4
    out = _block(n, KEY, c3=1)
    shifts = torch.arange(32, dtype=torch.int64)
    se = 0.5 / math.sqrt(n)
    for w, word in enumerate(out):
        frac = ((word.unsqueeze(1) >> shifts) & 1).sum(dim=0).double() / n
        for b in range(32):
            assert_z(float(frac[b]), 0.5, se, n_sigma=Z_SIGMA, what=f"word {w} bit {b}")


def _corr_se(n: int) -> float:
    """Standard error of Pearson's correlation of n independent pairs (rho = 0)."""
    return 1.0 / math.sqrt(n)


def _pair_counts(a: np.ndarray, b: np.ndarray, cells: int = 16) -> np.ndarray:
    ia = (a * cells).astype(np.int64)
    ib = (b * cells).astype(np.int64)
    return np.bincount(ia * cells + ib, minlength=cells * cells)


def test_words_of_a_block_uncorrelated(words):
    for i in range(4):
        for j in range(i + 1, 4):
            r = float(np.corrcoef(words[i], words[j])[0, 1])
            assert_z(r, 0.0, _corr_se(N_STAT), n_sigma=Z_SIGMA, what=f"corr(word {i}, word {j})")


@pytest.mark.parametrize("pair", [(0, 1), (1, 2), (2, 3), (0, 3)])
def test_words_of_a_block_pairs_chi2(words, pair):
    i, j = pair
    counts = _pair_counts(words[i], words[j])
    assert_chi2(counts, np.full(256, 1 / 256), N_STAT, n_tests=N_CHI2, what=f"pairs (word {i}, word {j})")


@pytest.mark.parametrize("axis", ["c0", "c2", "c3"])
def test_neighbouring_counters_independent(axis):
    """Serial correlation ~ 0 and uniform 2-D pairs between counters differing by 1 in one word.

    c0 is the photon index, c2 the draw (step) index, c3 the purpose: the walk's neighbours.
    """
    n = N_STAT // 4
    base = dict(c1=0, c2=9, c3=0)
    if axis == "c0":
        a = _block(n + 1, KEY, **base)[0]
        u, v = a[:-1], a[1:]
    else:
        bumped = dict(base, **{axis: base[axis] + 1})
        u = _block(n, KEY, **base)[0]
        v = _block(n, KEY, **bumped)[0]
    u = uniform_halfopen(u).double().numpy()
    v = uniform_halfopen(v).double().numpy()
    r = float(np.corrcoef(u, v)[0, 1])
    assert_z(r, 0.0, _corr_se(n), n_sigma=Z_SIGMA, what=f"serial correlation along {axis}")
    assert_chi2(_pair_counts(u, v), np.full(256, 1 / 256), n, n_tests=N_CHI2, what=f"pairs along {axis}")


def test_neighbouring_keys_independent():
    """Streams of two seeds' keys (and keys differing by one bit) look independent."""
    n = N_STAT // 4
    k_a = stream_key(1, "cfg")
    k_b = stream_key(2, "cfg")
    u = uniform_halfopen(_block(n, k_a)[0]).double().numpy()
    v = uniform_halfopen(_block(n, k_b)[0]).double().numpy()
    r = float(np.corrcoef(u, v)[0, 1])
    assert_z(r, 0.0, _corr_se(n), n_sigma=Z_SIGMA, what="correlation across seeds")
    w = uniform_halfopen(_block(n, (k_a[0] ^ 1, k_a[1]))[0]).double().numpy()
    assert_chi2(_pair_counts(u, w), np.full(256, 1 / 256), n, n_tests=N_CHI2, what="pairs across one key bit")


# --- stream keys ---------------------------------------------------------------------------------


def test_stream_key_deterministic_and_32_bit():
    a = stream_key(42, "g=0.9|eta=1.4|theta_i=0|ch=0")
    b = stream_key(42, "g=0.9|eta=1.4|theta_i=0|ch=0")
    assert a == b
    assert isinstance(a, tuple) and len(a) == 2
    for k in a:
        assert isinstance(k, int) and 0 <= k <= M32


def test_stream_key_differs_between_seeds_and_configs():
    cfgs = ["g=0.9|eta=1.4|theta_i=0|ch=0", "g=0.9|eta=1.4|theta_i=0|ch=1", "g=0.9|eta=1.4|theta_i=30|ch=0", ""]
    keys = {(s, c): stream_key(s, c) for s in (0, 1, 2, 12345, 2**40) for c in cfgs}
    assert len(set(keys.values())) == len(keys)
    # The seed and the configuration must not run together: (1, "2|x") is not (12, "|x").
    assert stream_key(1, "2") != stream_key(12, "")


def test_uniform_mappings_agree_on_int32_bit_patterns():
    """The walk passes int32 bit patterns (negative for words >= 2**31): same floats as int64."""
    x = torch.tensor([0, 1, 0x7FFFFFFF, 0x80000000, 0x80000100, 0xFFFFFF00, M32], dtype=torch.int64)
    assert torch.equal(uniform_open(to_i32(x)), uniform_open(x))
    assert torch.equal(uniform_halfopen(to_i32(x)), uniform_halfopen(x))
