"""The phase-function seam: what the walk, the hybrid and the connections ask of a phase function.

In pbrt's manner (pbrt-v4 ``PhaseFunction``: ``p``, ``Sample_p``, ``PDF``), on the
per-configuration parameter the walk carries (``g`` of :class:`workers.walk.walk.ConfigTable`,
in the lanes and in the estimators' geometry):

- ``sample_cos(u, g, branch)``: the cosine between the directions before and after scattering,
  from u uniform in [0, 1) (the azimuth is uniform and drawn by the caller); ``branch`` is a
  compile-time hint of the parameters' range (``WalkParams.hg_branch``);
- ``pdf(cos, g)``: the density per steradian of that sample (the connections' and the hybrid's
  MIS weights);
- ``evaluate(cos, g)``: the phase function's value per steradian (what a connection carries).

As in pbrt, a phase function samples itself exactly: pdf = evaluate, which the hybrid relies on
when it weights the walk's own direction.  Henyey-Greenstein (:mod:`workers.walk.optics`,
``sample_hg`` / ``hg_pdf``) is the one implementation today; its kernels are the same
operations as before the seam, so the compiled walk gives the same numbers.  The choice is a
compile-time constant (``WalkParams.phase``, ``ConnectionGeometry.phase``,
``FirstVertexGeometry.phase``), looked up by name in :data:`PHASE_FUNCTIONS`.

A new phase function is its module beside this one (the three functions above, torch only, no
data-dependent control flow, so it compiles), one line in :data:`PHASE_FUNCTIONS` and
:func:`phase_of`, and its schema entry (``schema/medium.py``: the medium's choice and its range),
plus its statistical test (its samples against its pdf, as ``tests/workers/test_optics_hg.py``
does for Henyey-Greenstein).  One with more than the one parameter per configuration also widens
the parameter row the walk carries (``ConfigTable``, ``workers/run/plan.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .optics import hg_pdf, sample_hg

__all__ = ["HenyeyGreenstein", "PHASE_FUNCTIONS", "DEFAULT_PHASE", "phase_function", "phase_of"]


@dataclass(frozen=True)
class HenyeyGreenstein:
    """p(cos) = (1 - g^2) / (4 pi (1 + g^2 - 2 g cos)^(3/2)), sampled by inverting its CDF
    (:func:`workers.walk.optics.hg_pdf`, :func:`workers.walk.optics.sample_hg`)."""

    name: str = "hg"

    def sample_cos(self, u: torch.Tensor, g: torch.Tensor, branch: str = "mixed") -> torch.Tensor:
        return sample_hg(u, g, branch)

    def pdf(self, cos_theta: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        return hg_pdf(cos_theta, g)

    def evaluate(self, cos_theta: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        return hg_pdf(cos_theta, g)


PHASE_FUNCTIONS = {"hg": HenyeyGreenstein()}
"""Every phase function the walk can compile, by the name the kernels' constants carry."""

DEFAULT_PHASE = "hg"


def phase_function(name: str):
    """The phase function called ``name`` (ValueError naming the known ones otherwise)."""
    try:
        return PHASE_FUNCTIONS[name]
    except KeyError:
        raise ValueError(f"phase function must be one of {sorted(PHASE_FUNCTIONS)}; received {name!r}") from None


def phase_of(spec) -> str:
    """The phase function of a spec's medium: Henyey-Greenstein for every medium today (the
    schema offers no other yet; the first other phase function returns the medium's choice here)."""
    return DEFAULT_PHASE
