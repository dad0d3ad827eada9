"""The fold's configurations without torch (workers/fold/configs.py).

The specular reflectance is computed in Python floats with a correctly rounded square root;
torch's float64 sqrt is not correctly rounded on every CPU (on an AVX-512 machine 94 of the
57 728 (theta, eta) pairs below differ in cos_t by one ulp), so the float64 value equals torch's
wherever torch's sqrt of the same argument is correctly rounded, and the walk's float32 entry
weight 1 - R is the same at every pair: the walk runs the same numbers.
"""

from __future__ import annotations

import math
import struct

import numpy as np
import torch

from workers.fold.configs import build_configs, specular_reflectance
from workers.measure.bench import _spec
from workers.run.plan import config_table
from workers.walk.optics import fresnel_dielectric


def _bits(x: float) -> bytes:
    return struct.pack("<d", x)


ETAS = sorted({*np.linspace(0.25, 4.0, 61).tolist(), 1.0, 1.3, 1.33, 1.5, 1 / 1.3})
THETAS = [*np.arange(0.0, 90.0, 0.1).tolist(), 89.999, 90.0]


def _torch_fresnel(theta: float, eta: float) -> float:
    return float(fresnel_dielectric(torch.tensor(math.cos(math.radians(theta)), dtype=torch.float64), eta))


def _torch_sqrt_rounds_correctly(theta: float, eta: float) -> bool:
    cos_i = min(max(math.cos(math.radians(theta)), 0.0), 1.0)
    cos2_t = 1.0 - (1.0 - cos_i * cos_i) / (eta * eta)
    return cos2_t <= 0.0 or float(torch.sqrt(torch.tensor(cos2_t, dtype=torch.float64))) == math.sqrt(cos2_t)


def test_specular_reflectance_is_the_torch_fresnel_with_a_correctly_rounded_sqrt():
    """Every incidence on a 0.1 degree grid (and the grazing end) for indices across the spec's
    range [0.25, 4], 1 (no interface) and the presets' 1.3, 1.33, 1.5: the same float64 bits as
    the walk's torch Fresnel wherever torch's sqrt rounds correctly, and everywhere the same
    float32 entry weight 1 - R that the walk carries."""
    same = 0
    for eta in ETAS:
        for theta in THETAS:
            want, got = _torch_fresnel(theta, eta), specular_reflectance(theta, eta)
            if _torch_sqrt_rounds_correctly(theta, eta):
                assert _bits(got) == _bits(want), (theta, eta, got, want)
                same += 1
            assert np.float32(1.0 - got) == np.float32(1.0 - want), (theta, eta, got, want)
    # The bitwise check must have run on nearly every pair.  How often torch's float64 sqrt misrounds
    # depends on the CPU's vector code: 94 of 57,728 pairs on an Intel Xeon (AVX-512), 817 on an
    # AMD EPYC (Zen 4); the float32 check above holds at every pair on both.
    assert same >= 0.95 * len(ETAS) * len(THETAS)


def test_specular_reflectance_of_the_examples_is_bitwise_the_torch_value():
    """The example specs' incidences (0, 45, 70 degrees) and indices (1.3, 1.33, 1.5)."""
    for theta in (0.0, 45.0, 70.0):
        for eta in (1.3, 1.33, 1.5):
            assert _bits(specular_reflectance(theta, eta)) == _bits(_torch_fresnel(theta, eta))


def test_config_table_entry_weight_is_one_minus_the_specular_reflectance():
    spec = _spec("M2", "exits", 1000).model_copy(update={"incidence_deg": [0.0, 30.0, 60.0]})
    cfgs = build_configs(spec)
    table = config_table(spec, cfgs)
    assert torch.equal(table.w0, torch.tensor([1.0 - r for r in cfgs.r_spec.tolist()], dtype=torch.float32))
    assert torch.equal(table.albedo, torch.tensor(cfgs.albedo, dtype=torch.float32))
    assert len(table.k0) == cfgs.n == 3 * len(cfgs.channel_names)
