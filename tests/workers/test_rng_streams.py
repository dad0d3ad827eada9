"""Tests of the walk's per-photon streams (workers/walk/rng.py): xoshiro128+ against the authors'
reference outputs, eager and compiled, and against plain Python; the start state against Philox;
uniformity and independence of a step's draws, of successive steps and of neighbouring photons.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.support.stats import assert_chi2, assert_z, z_threshold
from workers.walk import rng
from workers.walk.rng import philox4x32_scalar, stream_key, to_i32, to_u32, uniform_halfopen

M32 = 0xFFFFFFFF
N_STAT = 2**20
KEY = stream_key(20240917, "tests.rng")


def _corr_se(n: int) -> float:
    """Standard error of Pearson's correlation of n independent pairs (rho = 0)."""
    return 1.0 / math.sqrt(n)


def _pair_counts(a: np.ndarray, b: np.ndarray, cells: int = 16) -> np.ndarray:
    return np.bincount((a * cells).astype(np.int64) * cells + (b * cells).astype(np.int64), minlength=cells * cells)


# xoshiro128+ from the state (1, 2, 3, 4): the first ten outputs of the authors' reference C code.
XOSHIRO_KAT = ((1, 2, 3, 4), (5, 12295, 25178119, 27286542, 39879690, 1140358681, 3276312097, 4110231701, 399823256, 2144435200))
N_STREAM_Z = 3 + 32  # for the Sidak correction: neighbour correlations, bits of neighbouring photons
N_STREAM_CHI2 = 4 + 3  # word uniformity, neighbour pairs


def _state(values, n: int):
    return tuple(to_i32(torch.full((n,), v, dtype=torch.int64)) for v in values)


def test_xoshiro_scalar_known_answers():
    state, expected = XOSHIRO_KAT
    assert rng.xoshiro128p_scalar(state, 10)[0] == list(expected)


@pytest.mark.parametrize("compiled", [False, True], ids=["eager", "compiled"])
@pytest.mark.parametrize("n", [7, 800])  # a scalar loop and a vectorized one when compiled
def test_xoshiro_tensor_known_answers(compiled, n):
    """The tensor generator gives the reference outputs, eager and compiled (every 32-bit wrap of
    the add and the shifts kept), and the state after them equals the plain-Python one."""
    state, expected = XOSHIRO_KAT
    fn = rng.stream_draws
    if compiled:
        torch._dynamo.reset()
        fn = torch.compile(lambda s: rng.stream_draws(s, 10), dynamic=False, fullgraph=True)
        outs, after = fn(_state(state, n))
    else:
        outs, after = fn(_state(state, n), 10)
    assert [set(to_u32(o).tolist()) for o in outs] == [{e} for e in expected]
    ref_after = rng.xoshiro128p_scalar(state, 10)[1]
    assert [set(to_u32(s).tolist()) for s in after] == [{v} for v in ref_after]


def test_xoshiro_tensor_matches_scalar_on_random_states():
    rs = np.random.default_rng(11)
    states = rs.integers(0, 2**32, size=(300, 4), dtype=np.uint64).astype(np.int64)
    states[:4] = M32  # every add and shift at its wrap
    outs, _ = rng.stream_draws(tuple(to_i32(torch.from_numpy(states[:, j])) for j in range(4)), 6)
    got = np.stack([to_u32(o).numpy() for o in outs], axis=1)
    for i in range(len(states)):
        assert got[i].tolist() == rng.xoshiro128p_scalar(tuple(int(v) for v in states[i]), 6)[0]


def test_stream_start_is_the_philox_block_never_zero():
    """A photon's stream starts from Philox(photon, 0, purpose) with its second word made odd."""
    photon = torch.arange(1000, dtype=torch.int64)
    lo, hi = rng.photon_words(photon)
    k0, k1 = (torch.tensor(to_i32(torch.tensor(k)).item(), dtype=torch.int32) for k in KEY)
    start = rng.stream_start(lo, hi, 0, k0, k1)
    for i in (0, 1, 999):
        block = philox4x32_scalar((i, 0, 0, 0), KEY)
        assert tuple(int(to_u32(s[i])) for s in start) == (block[0], block[1] | 1, block[2], block[3])
    assert bool((start[1] & 1).all())


@pytest.fixture(scope="module")
def walk_streams():
    """Uniforms of 2**18 photons' walk streams, 12 steps of 4 draws each: [photon, step, word]."""
    from workers.walk.walk import walk_stream_start

    n, steps = N_STAT // 4, 12
    lo, hi = rng.photon_words(torch.arange(n, dtype=torch.int64))
    k = tuple(torch.tensor(to_i32(torch.tensor(v)).item(), dtype=torch.int32) for v in KEY)
    state = walk_stream_start(lo, hi, *k)
    out = np.empty((n, steps, 4))
    for s in range(steps):
        words, state = rng.stream_draws(state)
        for j, w in enumerate(words):
            out[:, s, j] = uniform_halfopen(w).double().numpy()
    return out


@pytest.mark.parametrize("word", range(4))
def test_walk_stream_words_uniform(walk_streams, word):
    """Each of a step's four draws, pooled over photons and steps, is uniform (256 cells)."""
    u = walk_streams[:, :, word].reshape(-1)
    counts = np.bincount((u * 256).astype(np.int64), minlength=256)
    assert_chi2(counts, np.full(256, 1 / 256), len(u), n_tests=N_STREAM_CHI2, what=f"walk stream word {word}")


@pytest.mark.parametrize("what", ["next word", "same word, next step", "same draw, next photon"])
def test_walk_stream_neighbours_independent(walk_streams, what):
    """Disjoint pairs of neighbouring draws -- words 0 and 1 and words 2 and 3 of a step, a word at
    an even step and the next step, the same draw of an even photon and the next photon -- are
    uniform on the unit square (16 x 16 cells) and uncorrelated."""
    u = walk_streams
    if what == "next word":
        a, b = u[:, :, 0::2].reshape(-1), u[:, :, 1::2].reshape(-1)
    elif what == "same word, next step":
        a, b = u[:, 0::2, :].reshape(-1), u[:, 1::2, :].reshape(-1)
    else:
        a, b = u[0::2, :, :].reshape(-1), u[1::2, :, :].reshape(-1)
    assert_chi2(_pair_counts(a, b), np.full(256, 1 / 256), len(a), n_tests=N_STREAM_CHI2, what=f"pairs: {what}")
    r = float(np.corrcoef(a, b)[0, 1])
    assert_z(r, 0.0, _corr_se(len(a)), n_sigma=z_threshold(N_STREAM_Z), what=f"correlation: {what}")


def test_walk_stream_first_step_draws_of_photons_differ_in_every_bit():
    """Neighbouring photons' first draws share no structure bit by bit: each bit of the xor of
    photon i's and photon i+1's first output is 1 half of the time."""
    from workers.walk.walk import walk_stream_start

    n = N_STAT // 4
    lo, hi = rng.photon_words(torch.arange(n + 1, dtype=torch.int64))
    k = tuple(torch.tensor(to_i32(torch.tensor(v)).item(), dtype=torch.int32) for v in KEY)
    (first, *_), _ = rng.stream_draws(walk_stream_start(lo, hi, *k))
    x = to_u32(first[:-1] ^ first[1:])
    frac = ((x.unsqueeze(1) >> torch.arange(32)) & 1).sum(dim=0).double() / n
    for b in range(32):
        assert_z(float(frac[b]), 0.5, 0.5 / math.sqrt(n), n_sigma=z_threshold(N_STREAM_Z), what=f"bit {b}")
