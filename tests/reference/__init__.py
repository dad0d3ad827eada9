"""Deterministic exact reference solutions used to validate the Monte Carlo walk.

Pure numpy/scipy (no torch), independent of ``workers/``. Conventions follow
``workers/walk/conventions.py``: the medium fills z < 0, the surface is z = 0 with outward
normal +z, outside index 1, relative index ``eta`` of the medium, lengths in mm
and coefficients in 1/mm. Reflectances are per unit incident power, i.e. they
include the entry transmission 1 - Fr(cos theta_i, eta).

Modules
-------
fresnel           exact unpolarised dielectric Fresnel reflectance (scalar and array)
hfunction         Chandrasekhar's H-function for isotropic scattering, plane albedo
single_scattering exact single-scattering reflectance, radial and directional profiles
"""
