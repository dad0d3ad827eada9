"""Physical ranges of the medium and bin fields: an absurd medium is refused naming the field and
its allowed range, and at the edges of every range the derived quantities (sigma_t, the transport
mean free path, radial edges in mm and in optical radii) are finite, positive and increasing."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from pydantic import ValidationError

from schema import SimulationSpec
from schema.bins import MAX_MFP_RANGE, MAX_MM_RANGE, MIN_FRACTION_RANGE, PBRT_MAX_COUNT
from schema.medium import COEFF_RANGE, ETA_RANGE, G_RANGE, SIGMA_T_RANGE


def spec(medium=None, radial=None, **kw) -> dict:
    d = {"name": "r", "medium": medium or {"sigma_a": 0.1, "sigma_s": 1.0, "eta": 1.3}}
    if radial is not None:
        d["bins"] = {"radial": radial}
    return d | kw


# The media of the hostile client (issue 21) and their neighbours: (spec, location, range text).
ABSURD = [
    ("eta-1e-300", spec({"sigma_a": 0.1, "sigma_s": 1.0, "eta": 1e-300}), "medium.eta", "[0.25, 4]"),
    ("eta-0.1", spec({"sigma_a": 0.1, "sigma_s": 1.0, "eta": 0.1}), "medium.eta", "[0.25, 4]"),
    ("sigma_a-subnormal-sigma_s-0", spec({"sigma_a": 1e-320, "sigma_s": 0, "eta": 1.3}), "medium",
     "sigma_t = sigma_a + sigma_s must be in the allowed range [1e-6, 1e6]"),
    ("sigma_s-1e308", spec({"sigma_a": 0.1, "sigma_s": 1e308, "eta": 1.3}), "medium.sigma_s", "[0, 1e6]"),
    ("both-1e300", spec({"sigma_a": 1e300, "sigma_s": 1e300, "eta": 1.3}), "medium.sigma_a", "[0, 1e6]"),
    ("sigma_t-over", spec({"sigma_a": 6e5, "sigma_s": 6e5, "eta": 1.3}), "medium", "[1e-6, 1e6]"),
    ("reduced-over", spec({"sigma_a": 0.1, "sigma_s_reduced": 1e4, "g": 0.999, "eta": 1.3}), "medium",
     "[1e-6, 1e6]"),
    ("scale-huge", spec({"preset": "marble", "scale": 1e300}), "medium.scale", "(0, 1e6]"),
    ("scale-tiny", spec({"preset": "marble", "scale": 1e-300}), "medium", "[1e-6, 1e6]"),
    ("g-near-one", spec({"sigma_a": 0.1, "sigma_s": 1.0, "g": 0.9999999, "eta": 1.3}), "medium.g",
     "[-0.999, 0.999]"),
    ("max_mfp-1e308", spec(radial={"max_mfp": 1e308}), "bins.radial.max_mfp", "[0.001, 10000]"),
    ("max_mfp-tiny", spec(radial={"max_mfp": 1e-300}), "bins.radial.max_mfp", "[0.001, 10000]"),
    ("max_mm-huge", spec(radial={"max_mm": 1e300}), "bins.radial.max_mm", "[1e-6, 1e6]"),
    ("min_fraction-tiny", spec(radial={"min_fraction": 1e-300}), "bins.radial.min_fraction", "[1e-9, 1)"),
    ("pbrt-4096", spec(radial={"spacing": "pbrt", "count": 4096}), "bins.radial", "[2, 100]"),
    ("sweep-eta", {"name": "r", "sweep": {"albedo": [0.5], "g": [0.0], "eta": [1e-300]}}, "sweep.eta.0",
     "[0.25, 4]"),
    ("sweep-g", {"name": "r", "sweep": {"albedo": [0.5], "g": [-0.9999], "eta": [1.3]}}, "sweep.g.0",
     "[-0.999, 0.999]"),
]


@pytest.mark.parametrize("data, loc, text", [a[1:] for a in ABSURD], ids=[a[0] for a in ABSURD])
def test_absurd_media_are_refused_naming_the_field_and_range(data, loc, text):
    with pytest.raises(ValidationError) as info:
        SimulationSpec.model_validate(data)
    errors = {".".join(map(str, e["loc"])): e["msg"] for e in info.value.errors()}
    assert loc in errors, errors
    assert text in errors[loc]
    assert "received" in errors[loc]


def _edges_are_sane(s: SimulationSpec) -> None:
    for c in s.channels():
        assert np.isfinite([c.sigma_t, c.albedo, c.sigma_t_reduced, c.transport_mfp_mm]).all()
        assert c.sigma_t > 0 and c.transport_mfp_mm > 0
    edges = s.radial_edges_mm()
    assert np.isfinite(edges).all() and np.all(np.diff(edges, axis=1) > 0)
    optical = edges * np.array([c.sigma_t for c in s.channels()])[:, None]
    area = np.pi * np.diff(edges**2, axis=1)
    assert np.isfinite(optical.astype(np.float32)).all() and np.all(optical.astype(np.float32)[:, 1:] > 0)
    assert np.isfinite(1.0 / area).all() and np.isfinite((1.0 / area) ** 2).all()  # Rd_r and its square


def _corners(r):
    """The extreme values of an interval that are allowed."""
    return [r.lo, r.hi]


@pytest.mark.parametrize("a, s, g", list(itertools.product(
    [0.0, COEFF_RANGE.hi / 2], [SIGMA_T_RANGE.lo, COEFF_RANGE.hi / 2], _corners(G_RANGE))))
@pytest.mark.parametrize("radial", [
    {"max_mfp": MAX_MFP_RANGE.lo, "min_fraction": MIN_FRACTION_RANGE.lo},
    {"max_mfp": MAX_MFP_RANGE.hi, "count": 4096},
    {"max_mm": MAX_MM_RANGE.lo, "min_fraction": MIN_FRACTION_RANGE.lo},
    {"max_mm": MAX_MM_RANGE.hi, "spacing": "linear", "count": 4096},
    {"spacing": "pbrt", "count": PBRT_MAX_COUNT},
])
def test_every_allowed_extreme_gives_finite_edges(a, s, g, radial):
    medium = {"sigma_a": a, "sigma_s": s, "g": g, "eta": ETA_RANGE.lo}
    try:
        parsed = SimulationSpec.model_validate(spec(medium, radial))
    except ValidationError as exc:  # only a sigma_t out of range may refuse a corner
        assert "sigma_t" in str(exc), exc
        return
    _edges_are_sane(parsed)
