"""The phase-function seam (workers/walk/phase.py): every registered phase function samples its
own pdf (chi-square, cell masses by quadrature of its pdf, never from the sampler), its pdf is
normalised over the sphere and equals its value (sampled exactly, as the hybrid assumes), and
Henyey-Greenstein through the seam is bitwise the optics kernels the walk compiled before it.
A new phase function registered in PHASE_FUNCTIONS is tested here by the same code."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import integrate

from tests.support.stats import assert_samples_match_pdf
from workers.walk.optics import hg_pdf, sample_hg
from workers.walk.phase import DEFAULT_PHASE, PHASE_FUNCTIONS, phase_function

G_VALUES = [-0.9, 0.0, 0.5, 0.9]
N_SAMPLES = 200_000
CASES = [(name, g) for name in sorted(PHASE_FUNCTIONS) for g in G_VALUES]


def _cos_pdf(phase, g: float):
    return lambda c: 2.0 * math.pi * float(phase.pdf(torch.tensor(c, dtype=torch.float64), torch.tensor(g, dtype=torch.float64)))


@pytest.mark.parametrize("name,g", CASES)
def test_samples_follow_the_pdf(name, g):
    phase = phase_function(name)
    u = torch.from_numpy(np.random.default_rng(11).random(N_SAMPLES))
    cos = phase.sample_cos(u, torch.full_like(u, g), "mixed").numpy()
    edges = np.linspace(-1.0, 1.0, 41)
    assert_samples_match_pdf(cos, _cos_pdf(phase, g), edges, n_tests=len(CASES), points=[1.0 if g > 0 else -1.0],
                             what=f"{name} g={g}")


@pytest.mark.parametrize("name,g", CASES)
def test_pdf_is_normalised_and_is_the_value(name, g):
    phase = phase_function(name)
    total, err = integrate.quad(_cos_pdf(phase, g), -1.0, 1.0, points=[1.0 if g > 0 else -1.0], epsabs=1e-13, limit=200)
    assert abs(total - 1.0) <= max(1e-9, 10 * err), (total, err)
    c = torch.linspace(-1.0, 1.0, 101, dtype=torch.float64)
    gg = torch.full_like(c, g)
    assert torch.equal(phase.pdf(c, gg), phase.evaluate(c, gg))


def test_henyey_greenstein_through_the_seam_is_the_walks_kernel():
    hg = phase_function(DEFAULT_PHASE)
    u = torch.from_numpy(np.random.default_rng(3).random(10_000, dtype=np.float32))
    g = torch.from_numpy(np.random.default_rng(4).uniform(-0.99, 0.99, 10_000).astype(np.float32))
    for branch in ("mixed", "large", "small"):
        assert torch.equal(hg.sample_cos(u, g, branch), sample_hg(u, g, branch))
    c = torch.from_numpy(np.random.default_rng(5).uniform(-1, 1, 10_000).astype(np.float32))
    assert torch.equal(hg.pdf(c, g), hg_pdf(c, g)) and torch.equal(hg.evaluate(c, g), hg_pdf(c, g))


def test_an_unknown_phase_function_is_refused_by_name():
    with pytest.raises(ValueError, match=r"phase function must be one of \['hg'\]; received 'rayleigh'"):
        phase_function("rayleigh")
