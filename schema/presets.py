"""Measured materials of Jensen, Marschner, Levoy and Hanrahan (2001).

Source: H. W. Jensen et al., "A Practical Model for Subsurface Light Transport", SIGGRAPH 2001,
table of measured parameters (also in the "Setting parameters" slide of the volume and
participating media lecture, and used by pbrt for its named media). Per R, G, B channel:

* ``sigma_s_reduced`` -- reduced scattering coefficient sigma_s' = sigma_s (1 - g), in 1/mm,
* ``sigma_a`` -- absorption coefficient, in 1/mm,
* ``eta`` -- relative index of refraction (1.3 for all but marble, 1.5).

The table's "diffuse reflectance" column is derived data and is not kept. The table gives
sigma_s', not sigma_s and g; a preset is turned into a medium with an assumed g (default 0, as
pbrt does), sigma_s = sigma_s' / (1 - g).
"""

from __future__ import annotations

from typing import NamedTuple

__all__ = ["Preset", "PRESETS", "PRESET_CHANNELS", "get_preset"]

RGB = tuple[float, float, float]


class Preset(NamedTuple):
    """One measured material: ``(sigma_s_reduced RGB [1/mm], sigma_a RGB [1/mm], eta)``."""

    sigma_s_reduced: RGB
    sigma_a: RGB
    eta: float


PRESET_CHANNELS: tuple[str, str, str] = ("R", "G", "B")
"""Channel names of every preset."""

# Transcribed from Jensen et al. 2001, table 2 (checked twice against the slide table).
#                      sigma_s' R, G, B [1/mm]     sigma_a R, G, B [1/mm]       eta
PRESETS: dict[str, Preset] = {
    "apple": Preset((2.29, 2.39, 1.97), (0.0030, 0.0034, 0.046), 1.3),
    "chicken1": Preset((0.15, 0.21, 0.38), (0.015, 0.077, 0.19), 1.3),
    "chicken2": Preset((0.19, 0.25, 0.32), (0.018, 0.088, 0.20), 1.3),
    "cream": Preset((7.38, 5.47, 3.15), (0.0002, 0.0028, 0.0163), 1.3),
    "ketchup": Preset((0.18, 0.07, 0.03), (0.061, 0.97, 1.45), 1.3),
    "marble": Preset((2.19, 2.62, 3.00), (0.0021, 0.0041, 0.0071), 1.5),
    "potato": Preset((0.68, 0.70, 0.55), (0.0024, 0.0090, 0.12), 1.3),
    "skimmilk": Preset((0.70, 1.22, 1.90), (0.0014, 0.0025, 0.0142), 1.3),
    "skin1": Preset((0.74, 0.88, 1.01), (0.032, 0.17, 0.48), 1.3),
    "skin2": Preset((1.09, 1.59, 1.79), (0.013, 0.070, 0.145), 1.3),
    "spectralon": Preset((11.6, 20.4, 14.9), (0.00, 0.00, 0.00), 1.3),
    "wholemilk": Preset((2.55, 3.21, 3.77), (0.0011, 0.0024, 0.014), 1.3),
}
"""Preset name (lower case) -> :class:`Preset`. Lookup through :func:`get_preset` ignores case."""


def get_preset(name: str) -> Preset:
    """The preset called ``name`` (case-insensitive); ``KeyError`` listing the names otherwise."""
    try:
        return PRESETS[name.lower()]
    except KeyError:
        raise KeyError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}") from None
