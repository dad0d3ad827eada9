"""What the fold knows of a spec's run without the walk: its configurations and its bins.

A configuration is one incidence angle x one channel, c = incidence index * n_channels + channel
(:class:`Configs`, numpy); the bins are :class:`BinLayout`.  The walk's own per-configuration
tables (float32 tensors, Philox keys, entry directions) are built from these in the run wing
(:func:`workers.run.plan.config_table`); nothing here imports torch, so a merge, a publish or a
reader of the tables runs without it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from schema import SimulationSpec

__all__ = ["BinLayout", "Configs", "bin_layout", "build_configs", "specular_reflectance"]


def specular_reflectance(theta_deg: float, eta: float) -> float:
    """Unpolarised Fresnel reflectance of the smooth surface for light incident at theta_deg
    from the outside (eta = n_medium / n_outside), in float64.

    The formula of :func:`workers.walk.optics.fresnel_dielectric` (Born and Wolf, sec. 1.5), the
    same operations in the same order on Python floats, so the value is bitwise the walk's
    (tested): Fr = (r_s^2 + r_p^2) / 2, 1 under total internal reflection, 0 without interface.
    """
    cos_i = min(max(math.cos(math.radians(theta_deg)), 0.0), 1.0)
    if eta == 1.0:
        return 0.0
    cos2_t = 1.0 - (1.0 - cos_i * cos_i) / (eta * eta)
    if cos2_t <= 0.0:
        return 1.0
    cos_t = math.sqrt(cos2_t)
    r_s = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    r_p = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    return 0.5 * (r_s * r_s + r_p * r_p)


@dataclass(frozen=True)
class Configs:
    """Per-configuration constants; configuration c = incidence index * n_channels + channel."""

    incidence_deg: list[float]
    channel_names: list[str]
    sigma_t: np.ndarray  # [n_cfg] 1/mm
    albedo: np.ndarray
    g: np.ndarray
    r_spec: np.ndarray  # specular reflectance at entry
    eta: float

    @property
    def n(self) -> int:
        return len(self.sigma_t)

    def channel_of(self, c: int) -> int:
        return c % len(self.channel_names)

    def incidence_of(self, c: int) -> float:
        return self.incidence_deg[c // len(self.channel_names)]


def build_configs(spec: SimulationSpec) -> Configs:
    """The spec's configurations in order c = incidence index * n_channels + channel."""
    channels = spec.channels()
    eta = float(spec.medium.eta)
    rows = [(ch.sigma_t, ch.albedo, ch.g, specular_reflectance(theta, eta)) for theta in spec.incidence_deg for ch in channels]
    cols = list(zip(*rows))
    return Configs(
        incidence_deg=list(spec.incidence_deg), channel_names=[c.name for c in channels],
        sigma_t=np.array(cols[0]), albedo=np.array(cols[1]), g=np.array(cols[2]), r_spec=np.array(cols[3]), eta=eta,
    )  # fmt: skip


@dataclass(frozen=True)
class BinLayout:
    """Edges of every bin axis; radial edges per channel in mm.

    radial_mm: float64 [n_channels, n_r + 1]; theta_s, cos_o, phi_o: float64 1-D edge arrays
    (theta_s and phi_o centred on 0: :func:`schema.bins.azimuth_edges`).
    The walk's lookups are :func:`workers.walk.binning.uniform_index`,
    :func:`workers.walk.binning.azimuth_index` and :mod:`workers.walk.harvest`; the searched
    reference they are tested against is in tests/reference/binning.py.
    """

    radial_mm: np.ndarray
    theta_s: np.ndarray
    cos_o: np.ndarray
    phi_o: np.ndarray

    @property
    def n_r(self) -> int:
        return self.radial_mm.shape[1] - 1

    @property
    def n_theta(self) -> int:
        return len(self.theta_s) - 1

    @property
    def n_cos(self) -> int:
        return len(self.cos_o) - 1

    @property
    def n_phi(self) -> int:
        return len(self.phi_o) - 1

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """(n_r + 1 with overflow, n_theta, n_cos, n_phi): the per-component histogram shape."""
        return (self.n_r + 1, self.n_theta, self.n_cos, self.n_phi)

    def area_mm2(self, channel: int) -> np.ndarray:
        """Area of each spatial bin [n_r, n_theta] in mm^2: (r_hi^2 - r_lo^2)/2 * dtheta_s."""
        r = self.radial_mm[channel]
        return np.outer(0.5 * (r[1:] ** 2 - r[:-1] ** 2), np.diff(self.theta_s))

    def solid_angle(self) -> np.ndarray:
        """Solid angle of each directional bin [n_cos, n_phi] in sr: dcos * dphi."""
        return np.outer(np.diff(self.cos_o), np.diff(self.phi_o))


def bin_layout(spec: SimulationSpec) -> BinLayout:
    return BinLayout(spec.radial_edges_mm(), spec.theta_s_edges(), spec.cos_theta_o_edges(), spec.phi_o_edges())
