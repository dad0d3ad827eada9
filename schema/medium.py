"""The medium: per-channel optical coefficients, phase function and relative index.

Conventions (workers/walk/conventions.py, "Geometry"): the medium fills z < 0 below the surface
z = 0; coefficients are in 1/mm; the phase function is Henyey-Greenstein with parameter g
(mean cosine, |g| < 1); ``eta`` is the medium's index relative to the outside (index 1), eta < 1
allowed.

A medium is given in exactly one of three forms; each form resolves to one
:class:`ChannelOptics` per spectral channel (:meth:`MediumSpec.channels`):

1. ``sigma_a``, ``sigma_s``, optional ``g`` (default 0), required ``eta``;
2. ``sigma_a``, ``sigma_s_reduced``, optional ``g`` (default 0), required ``eta``:
   sigma_s = sigma_s_reduced / (1 - g);
3. ``preset`` (a measured material of :mod:`schema.presets`, case-insensitive), optional ``scale``
   (> 0, multiplies sigma_a and sigma_s', default 1), ``g`` (default 0; sigma_s = sigma_s'/(1-g))
   and ``eta`` (default: the preset's).

Coefficients and ``g`` are per-channel lists (1..16 entries) or scalars, which broadcast to the
channel count. After validation the model is normalised: every per-channel field that applies is a
list of the full length, ``g``, ``eta``, ``channel_names`` (and ``scale`` for presets) are filled
in, the preset name is lower case. So equivalent inputs dump to the same JSON.
"""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, model_validator
from pydantic_core import PydanticCustomError

from .constraints import Interval, PerChannel
from .names import CHANNEL_NAME_MAX, InvalidName, check_name
from .presets import PRESET_CHANNELS, PRESETS, get_preset

__all__ = ["ChannelOptics", "MediumSpec", "ETA_RANGE", "G_RANGE", "COEFF_RANGE", "SIGMA_T_RANGE", "SCALE_RANGE"]

# Physical ranges (docs/architecture.md, "Physical ranges"). Every derived quantity of a medium
# inside them (sigma_t, albedo, the transport mean free path, radii in mm and in optical radii,
# bin areas and their squares) is a finite, normal float64, and float32 in the walk.
ETA_RANGE = Interval(0.25, 4.0, what="eta (relative index)")
"""Relative index n_medium / n_outside: real indices run from 1 (air) to about 4 (germanium in the
infrared; the highest in the visible, rutile, is 2.9), and the interface may be either way round."""
G_RANGE = Interval(-0.999, 0.999, what="g (HG mean cosine)")
"""HG mean cosine: the walk holds g in float32, which resolves 1 - |g| to 1e-4 here (at 1 - 1e-7 it
rounds to 0); measured media (tissue, milk, clouds) stay below 0.99."""
COEFF_RANGE = Interval(0.0, 1e6, what="coefficient [1/mm]")
"""sigma_a, sigma_s, sigma_s' [1/mm]: at 1e6/mm a mean free path is 1 nm, far below the wavelength
of light, where radiative transfer no longer describes a medium."""
SIGMA_T_RANGE = Interval(1e-6, 1e6, what="sigma_t = sigma_a + sigma_s [1/mm]")
"""Extinction [1/mm] of every channel: a mean free path from 1 nm to 1 km (the clearest water has
sigma_t of about 1e-5/mm)."""
SCALE_RANGE = Interval(0.0, 1e6, lo_open=True, what="scale")
"""A preset's factor on sigma_a and sigma_s' (unit changes); sigma_t is checked after it."""


def _coeff(what: str) -> Any:
    """``float | list[float]`` of finite coefficients in :data:`COEFF_RANGE` [1/mm]."""
    return Annotated[float | list[float], PerChannel(Interval(COEFF_RANGE.lo, COEFF_RANGE.hi, what=f"{what} [1/mm]"))]


PerChannelG = Annotated[float | list[float], PerChannel(G_RANGE)]
_PER_CHANNEL = ("sigma_a", "sigma_s", "sigma_s_reduced", "g")


class ChannelOptics(BaseModel):
    """Resolved optics of one spectral channel (all coefficients in 1/mm)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    sigma_a: float
    sigma_s: float
    g: float

    @property
    def sigma_t(self) -> float:
        """Extinction coefficient sigma_t = sigma_a + sigma_s [1/mm]."""
        return self.sigma_a + self.sigma_s

    @property
    def albedo(self) -> float:
        """Single-scattering albedo sigma_s / sigma_t, in [0, 1]."""
        return self.sigma_s / self.sigma_t

    @property
    def sigma_s_reduced(self) -> float:
        """Reduced scattering coefficient sigma_s' = sigma_s (1 - g) [1/mm]."""
        return self.sigma_s * (1.0 - self.g)

    @property
    def sigma_t_reduced(self) -> float:
        """Reduced extinction sigma_t' = sigma_a + sigma_s' [1/mm]."""
        return self.sigma_a + self.sigma_s_reduced

    @property
    def transport_mfp_mm(self) -> float:
        """Transport mean free path 1 / sigma_t' [mm]."""
        return 1.0 / self.sigma_t_reduced


def _form_error(message: str, **ctx: Any) -> PydanticCustomError:
    return PydanticCustomError("medium_form", message, ctx)


class MediumSpec(BaseModel):
    """Optical properties of the homogeneous medium (see the module docstring for the forms)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    preset: str | None = Field(
        None, description=f"Measured material (Jensen et al. 2001): {', '.join(PRESETS)}."
    )
    scale: Annotated[float, SCALE_RANGE] | None = Field(
        None, description="Preset only: factor on sigma_a and sigma_s' (e.g. unit changes). "
        "Default 1."
    )
    sigma_a: _coeff("sigma_a") | None = Field(None, description="Absorption coefficient [1/mm].")
    sigma_s: _coeff("sigma_s") | None = Field(None, description="Scattering coefficient [1/mm].")
    sigma_s_reduced: _coeff("sigma_s_reduced") | None = Field(
        None, description="Reduced scattering coefficient sigma_s (1 - g) [1/mm]."
    )
    g: PerChannelG | None = Field(None, description=f"HG mean cosine, in {G_RANGE}. Default 0.")
    eta: Annotated[float, ETA_RANGE] | None = Field(
        None, description=f"Relative index of refraction, in {ETA_RANGE}. Required unless preset."
    )
    channel_names: list[str] | None = Field(
        None, description='Unique channel names; default "R","G","B" for presets, else c0, c1...'
    )

    @model_validator(mode="after")
    def _resolve_form(self) -> MediumSpec:
        """Check that exactly one form is given, then normalise (see module docstring)."""
        explicit = [f for f in ("sigma_a", "sigma_s", "sigma_s_reduced") if _given(self, f)]
        if self.preset is not None:
            self._check_preset(explicit)
            n = len(PRESET_CHANNELS)
        else:
            self._check_explicit(explicit)
            n = _channel_count(self)
        updates: dict[str, Any] = {}
        for f in _PER_CHANNEL:
            v = getattr(self, f)
            if v is None:
                continue
            if isinstance(v, list) and len(v) != n:
                raise _form_error(
                    "channel lists must have equal lengths (a scalar broadcasts): {field} has "
                    "{got} entries, expected {n}", field=f, got=len(v), n=n)
            updates[f] = [float(x) for x in v] if isinstance(v, list) else [float(v)] * n
        updates.setdefault("g", [0.0] * n)
        updates["channel_names"] = self._names(n)
        if self.preset is not None:
            preset = get_preset(self.preset)
            updates["preset"] = self.preset.lower()
            updates["scale"] = 1.0 if self.scale is None else self.scale
            updates["eta"] = preset.eta if self.eta is None else self.eta
        for k, v in updates.items():
            # The model is frozen; normalising during its own validation is the one exception.
            object.__setattr__(self, k, v)
        self._check_extinction()
        return self

    def _check_preset(self, explicit: list[str]) -> None:
        if self.preset.lower() not in PRESETS:
            raise _form_error("preset {value} is not one of the allowed names: {names}",
                              value=repr(self.preset), names=", ".join(PRESETS))
        if explicit:
            raise _form_error(
                "give either preset or explicit coefficients, not both; received preset "
                "together with {fields}", fields=", ".join(explicit))

    def _check_explicit(self, explicit: list[str]) -> None:
        forms = ("give exactly one medium form: (1) sigma_a + sigma_s [+ g] + eta, "
                 "(2) sigma_a + sigma_s_reduced [+ g] + eta, or (3) preset [+ scale, g, eta]")
        if self.sigma_a is None or (self.sigma_s is None) == (self.sigma_s_reduced is None):
            raise _form_error(forms + "; received {fields}",
                              fields=", ".join(explicit) or "no coefficients")
        if self.scale is not None:
            raise _form_error("scale applies to presets only; received scale={value}",
                              value=self.scale)
        if self.eta is None:
            raise _form_error("eta (relative index, allowed range {allowed}) is required when the "
                              "coefficients are given explicitly; received none", allowed=str(ETA_RANGE))

    def _names(self, n: int) -> list[str]:
        if self.channel_names is None:
            return list(PRESET_CHANNELS) if self.preset is not None else [f"c{i}" for i in range(n)]
        names = self.channel_names
        if len(names) != n:
            raise _form_error("channel_names must have one name per channel ({n}); received "
                              "{got} names", n=n, got=len(names))
        if len(set(names)) != len(names):
            raise _form_error("channel_names must be unique; received {names}", names=repr(names))
        for name in names:
            try:
                check_name(name, "channel_names entries", CHANNEL_NAME_MAX)
            except InvalidName as exc:
                raise _form_error("{problem}", problem=str(exc)) from None
        return list(names)

    def _check_extinction(self) -> None:
        for c in self.channels():
            if not SIGMA_T_RANGE.contains(c.sigma_t):
                raise _form_error(
                    "sigma_t = sigma_a + sigma_s must be in the allowed range {allowed} in every "
                    "channel; received channel {name} with sigma_a = {a}, sigma_s = {s}",
                    allowed=str(SIGMA_T_RANGE), name=c.name, a=c.sigma_a, s=c.sigma_s)

    @property
    def n_channels(self) -> int:
        """Number of spectral channels."""
        return len(self.channel_names)

    def channels(self) -> list[ChannelOptics]:
        """One :class:`ChannelOptics` per channel, in order, resolved from the form given."""
        n = self.n_channels
        g = self.g
        if self.preset is not None:
            p = get_preset(self.preset)
            a = [x * self.scale for x in p.sigma_a]
            s_red = [x * self.scale for x in p.sigma_s_reduced]
            s = [sr / (1.0 - gi) for sr, gi in zip(s_red, g)]
        elif self.sigma_s is not None:
            a, s = self.sigma_a, self.sigma_s
        else:
            a = self.sigma_a
            s = [sr / (1.0 - gi) for sr, gi in zip(self.sigma_s_reduced, g)]
        return [
            ChannelOptics(name=self.channel_names[i], sigma_a=a[i], sigma_s=s[i], g=g[i])
            for i in range(n)
        ]


def _given(m: MediumSpec, field: str) -> bool:
    return getattr(m, field) is not None


def _channel_count(m: MediumSpec) -> int:
    """Channel count of an explicit medium: the longest list among the per-channel fields."""
    lengths = [len(v) for f in _PER_CHANNEL if isinstance(v := getattr(m, f), list)]
    return max(lengths, default=1)  # each list is already limited to MAX_CHANNELS entries
