"""The ``albedo-map`` export: single-scattering albedo -> total diffuse reflectance, measured.

Renderers that take "surface colour + mean free path" (Cycles, Arnold, RenderMan, pbrt-v4's
``reflectance``) must turn a colour into a single-scattering albedo; they use fitted curves.
This map is the measured relation at one (g, eta), per estimator, from every medium/channel of
the dataset at that (g, eta) (a sweep's albedo axis):

* ``rd_normal``: total diffuse reflectance Rd (specular excluded) per unit incident power at
  normal incidence, with its standard error; ``rho_eff_normal`` = Rd / (1 - R_spec), per unit
  power entered (pbrt's rhoEff convention, and the models' below);
* ``rd_diffuse``: under diffuse (cosine-weighted hemispherical) illumination,
  Rd_diffuse = int_0^1 Rd(mu) 2 mu dmu, mu = cos theta_i, by the n-point Gauss-Legendre rule in
  mu on [0, 1] when the dataset's incidence angles hold its nodes (:func:`diffuse_incidence_deg`
  gives them: put them in the spec's ``incidence_deg``), standard error
  sqrt(sum w_k^2 se_k^2) (angles have independent random streams), and
  ``rd_diffuse_quadrature_error``, an estimate: the rule's relative error on the entry
  transmittance 2 mu (1 - Fr(mu, eta)), whose integral is known, times Rd_diffuse. NaN when the
  angles hold no such rule (the metadata says which angles to add);
* ``*_monotone``: the weighted (1/se^2) isotonic regression of each measured curve (pool
  adjacent violators): equal to the measurement where it is already increasing, otherwise the
  closest non-decreasing curve; invert it with :func:`albedo_for_reflectance`: a monotone cubic
  (Fritsch-Carlson, PCHIP) of s = sqrt(1 - alpha') against the reflectance, alpha' the reduced
  albedo. Diffusion makes the reflectance a smooth function of s (R ~ 1 - sqrt(3) s near
  alpha' = 1), where it is a square root of the albedo, so straight lines in albedo are far off
  between sparse rows: on a 4-albedo table (0.5, 0.9, 0.99, 0.999; g 0, eta 1) linear
  interpolation in albedo is 19 % off in reflectance at Rd 0.2, pbrt's InvertCatmullRom 14 %,
  this inversion 5 % (tests/workers/test_export_albedo_map.py measures it against the exact
  half-space relation);
* the classical dipole's total reflectance (Jensen et al. 2001; normal incidence, per unit power
  entered) and Christensen-Burley's fitted relation (2015; which fits diffuse illumination of an
  index-matched isotropic half space, :func:`workers.models.diffusion.burley_reduced_albedo`), both at
  the reduced albedo alpha' = alpha (1 - g) / (1 - alpha g) as renderers apply them, with their
  error (model - measured) against ``rho_eff_normal`` and its z-score, and against
  ``rd_diffuse`` (what a diffusely lit surface shows);
* ``truncated_normal``: the weight cut at the path cap (``max_scatter``), which rd_normal misses.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from workers.models.diffusion import (
    albedo_from_reduced,
    burley_total_rd,
    dipole_total_rd,
    fresnel_moment,
    fresnel_reflectance,
    reduced_albedo,
)

from .profiles import summary_rows
from .source import ExportError, ExportSource

__all__ = ["AlbedoMap", "albedo_maps", "write_albedo_map", "diffuse_incidence_deg", "isotonic",
           "albedo_for_reflectance", "pchip", "pchip_slopes", "COLUMNS", "DEFINITIONS", "MAX_RULE"]

MAX_RULE = 16
"""Largest Gauss-Legendre rule looked for among a dataset's incidence angles."""
COLUMNS = ("albedo", "rd_normal", "rd_normal_stderr", "rho_eff_normal", "rho_eff_normal_stderr", "rd_normal_monotone",
           "rd_diffuse", "rd_diffuse_stderr", "rd_diffuse_quadrature_error", "rd_diffuse_monotone",
           "dipole_rho_eff", "dipole_error", "dipole_z", "dipole_error_diffuse",
           "burley_rho_eff", "burley_error", "burley_z", "burley_error_diffuse", "truncated_normal",
           "truncated_normal_stderr", "photons")


DEFINITIONS = {
    "rd_normal": "total diffuse reflectance (specular excluded) per unit incident power, normal incidence",
    "rho_eff_normal": "rd_normal / (1 - R_spec): per unit power entered (pbrt's rhoEff; the models' convention)",
    "rd_diffuse": "int_0^1 Rd(mu) 2 mu dmu under cosine-weighted hemispherical illumination (Gauss-Legendre in mu)",
    "rd_diffuse_quadrature_error": "estimate: the rule's relative error on 2 mu (1 - Fr(mu, eta)) times rd_diffuse",
    "*_monotone": "weighted (1/se^2) isotonic regression of the measured curve; invert by a monotone cubic (PCHIP) of "
                  "sqrt(1 - reduced albedo) against it (workers/exports/albedo_map.py albedo_for_reflectance)",
    "dipole_rho_eff": "classical dipole total reflectance (Jensen et al. 2001) at alpha' = alpha (1-g) / (1 - alpha g)",
    "burley_rho_eff": "Christensen-Burley (2015) fitted relation, inverted, at the same alpha' (it fits diffuse "
                      "illumination of an index-matched isotropic half space)",
    "*_error": "model - rho_eff_normal", "*_z": "*_error / rho_eff_normal_stderr",
    "*_error_diffuse": "model - rd_diffuse",
    "truncated_normal": "weight still alive at the path cap max_scatter per unit incident power, normal incidence: "
                        "missing from rd_normal (albedo 1 needs the cap); NaN error where no path reached it",
}
"""Meaning of each column (also written into the export's JSON)."""


def _gauss_legendre_mu(n: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (x + 1.0), 0.5 * w


def diffuse_incidence_deg(n: int) -> list[float]:
    """Incidence angles [deg] of the n-point Gauss-Legendre rule in mu = cos theta_i on [0, 1],
    ascending: the angles a spec needs for the diffuse-illumination column."""
    mu, _ = _gauss_legendre_mu(n)
    return sorted(float(np.degrees(np.arccos(m))) for m in mu)


def _rule_in(angles: list[float]) -> tuple[int, np.ndarray, np.ndarray] | None:
    """The largest n <= MAX_RULE whose nodes are all among ``angles`` (within 1e-6 deg):
    (n, indices of the angles, weights w_k 2 mu_k), or None."""
    a = np.asarray(angles, dtype=np.float64)
    for n in range(MAX_RULE, 0, -1):
        mu, w = _gauss_legendre_mu(n)
        idx = [int(np.argmin(np.abs(a - np.degrees(np.arccos(m))))) for m in mu]
        if all(abs(a[i] - np.degrees(np.arccos(m))) < 1e-6 for i, m in zip(idx, mu)):
            return n, np.array(idx), 2.0 * mu * w
    return None


def isotonic(y, se) -> np.ndarray:
    """Weighted isotonic (non-decreasing) regression by pool-adjacent-violators, weights 1/se^2
    (se = 0: an exact value, weight 1e30; se NaN: no information, weight 1e-30)."""
    y = np.asarray(y, dtype=np.float64)
    se = np.asarray(se, dtype=np.float64)
    w = np.where(np.isnan(se), 1e-30, 1.0 / np.maximum(se, 1e-15) ** 2)
    blocks: list[list[float]] = []  # [value, weight, count]
    for yi, wi in zip(y, w):
        blocks.append([yi, wi, 1])
        while len(blocks) > 1 and blocks[-2][0] > blocks[-1][0]:
            v2, w2, n2 = blocks.pop()
            v1, w1, n1 = blocks.pop()
            blocks.append([(v1 * w1 + v2 * w2) / (w1 + w2), w1 + w2, n1 + n2])
    return np.concatenate([[v] * n for v, _w, n in blocks])


def pchip_slopes(x, y) -> np.ndarray:
    """Fritsch-Carlson slopes of the monotone piecewise cubic Hermite interpolant through (x, y),
    x increasing: the weighted harmonic mean of the neighbouring secants where they agree in sign,
    0 where they do not (a local extremum stays one); at the ends the three-point estimate,
    limited so the ends do not overshoot. The cubic through those slopes is monotone wherever
    the data are."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    h, d = np.diff(x), np.diff(y) / np.diff(x)
    m = np.zeros_like(x)
    if len(x) == 2:
        return np.full(2, d[0])
    w1, w2 = 2 * h[1:] + h[:-1], h[1:] + 2 * h[:-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        inner = (w1 + w2) / (w1 / d[:-1] + w2 / d[1:])
    m[1:-1] = np.where(d[:-1] * d[1:] > 0, inner, 0.0)
    for end, (h0, h1, d0, d1) in ((0, (h[0], h[1], d[0], d[1])), (-1, (h[-1], h[-2], d[-1], d[-2]))):
        s = ((2 * h0 + h1) * d0 - h0 * d1) / (h0 + h1)
        if np.sign(s) != np.sign(d0):
            s = 0.0
        elif np.sign(d0) != np.sign(d1) and abs(s) > abs(3 * d0):
            s = 3 * d0
        m[end] = s
    return m


def pchip(x, y, xq) -> np.ndarray:
    """The monotone cubic of :func:`pchip_slopes` at xq (clamped to [x_0, x_{n-1}])."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    xq = np.clip(np.asarray(xq, dtype=np.float64), x[0], x[-1])
    m = pchip_slopes(x, y)
    i = np.clip(np.searchsorted(x, xq, side="right") - 1, 0, len(x) - 2)
    h = x[i + 1] - x[i]
    t = (xq - x[i]) / h
    return ((2 * t**3 - 3 * t**2 + 1) * y[i] + (t**3 - 2 * t**2 + t) * h * m[i] + (-2 * t**3 + 3 * t**2) * y[i + 1]
            + (t**3 - t**2) * h * m[i + 1])


def albedo_for_reflectance(albedo, monotone_rd, target, g: float = 0.0) -> np.ndarray:
    """Invert a map: the albedo whose (monotone) reflectance is ``target``, elementwise. s =
    sqrt(1 - alpha') (alpha' = alpha (1 - g) / (1 - alpha g), the reduced albedo) is interpolated
    against the reflectance by the monotone cubic :func:`pchip` and turned back into alpha =
    alpha' / (1 - g + alpha' g); exact at the map's points, clamped to its ends. A pooled flat
    stretch (equal reflectances) gives its first albedo; NaN entries are ignored."""
    a = np.asarray(albedo, dtype=np.float64)
    rd = np.asarray(monotone_rd, dtype=np.float64)
    keep = np.isfinite(rd) & np.isfinite(a)
    a, rd = a[keep], rd[keep]
    first = np.concatenate([[True], np.diff(rd) > 0])  # the first albedo of each flat stretch
    a, rd = a[first], rd[first]
    if len(a) == 1:
        return np.full(np.shape(target), a[0])
    s = np.sqrt(np.maximum(1.0 - reduced_albedo(a, g), 0.0))
    return albedo_from_reduced(1.0 - pchip(rd, s, target) ** 2, g)


@dataclass(frozen=True)
class AlbedoMap:
    """One (estimator, g, eta) map: ``columns[name]`` arrays over the albedos (:data:`COLUMNS`)."""

    estimator: str
    g: float
    eta: float
    columns: dict[str, np.ndarray]
    meta: dict[str, Any] = field(default_factory=dict)


def albedo_maps(source: ExportSource) -> list[AlbedoMap]:
    """Every (estimator, g, eta) map of the dataset (component total)."""
    rows = summary_rows(source.tables["summary"])
    angles = sorted({inc for (_e, _m, inc, _c, _k) in rows})
    if 0.0 not in angles:
        raise ExportError(f"the albedo map needs normal incidence (0 in incidence_deg); {source.label} has {angles}")
    rule = _rule_in(angles)
    groups: dict[tuple, dict] = {}
    for (est, medium, inc, channel, comp), row in rows.items():
        if comp == "total":
            groups.setdefault((est, row["g"], row["eta"]), {}).setdefault((medium, channel), {})[inc] = row
    return [_map(source, est, g, eta, list(series.values()), angles, rule) for (est, g, eta), series in sorted(groups.items())]


def _map(source, est, g, eta, series, angles, rule) -> AlbedoMap:
    series.sort(key=lambda by_angle: by_angle[0.0]["albedo"])
    albedo = np.array([s[0.0]["albedo"] for s in series])
    if len(albedo) < 2 or len(np.unique(albedo)) != len(albedo):
        raise ExportError(f"an albedo map needs at least 2 distinct albedos at (g, eta) = ({g}, {eta}); {source.label} "
                          f"has {albedo.tolist()[:8]} ({est}): measure a sweep over albedo")
    normal = [s[0.0] for s in series]
    rd = np.array([r["Rd"] for r in normal])
    rd_se = np.array([r["Rd_stderr"] for r in normal])
    entered = 1.0 - np.array([r["R_spec"] for r in normal])
    cols: dict[str, np.ndarray] = {"albedo": albedo, "rd_normal": rd, "rd_normal_stderr": rd_se,
                                   "rho_eff_normal": rd / entered, "rho_eff_normal_stderr": rd_se / entered,
                                   "rd_normal_monotone": isotonic(rd, rd_se),
                                   "truncated_normal": np.array([r["truncated"] for r in normal]),
                                   "truncated_normal_stderr": np.array([r["truncated_stderr"] for r in normal]),
                                   "photons": np.array([float(r["photons"]) for r in normal])}
    nan = np.full(len(albedo), np.nan)
    if rule is None:
        cols.update(rd_diffuse=nan, rd_diffuse_stderr=nan, rd_diffuse_quadrature_error=nan, rd_diffuse_monotone=nan)
    else:
        n, idx, weights = rule
        by = np.array([[s[angles[k]]["Rd"] for k in idx] for s in series])
        by_se = np.array([[s[angles[k]]["Rd_stderr"] for k in idx] for s in series])
        diffuse = by @ weights
        mu, _ = _gauss_legendre_mu(n)
        t_rule = float(np.sum(weights * (1.0 - fresnel_reflectance(mu, eta))))
        t_exact = 1.0 - 2.0 * fresnel_moment(1, 1.0 / eta)  # int 2 mu (1 - Fr(mu, eta)) dmu, entering
        se = np.sqrt((by_se**2) @ weights**2)
        cols.update(rd_diffuse=diffuse, rd_diffuse_stderr=se,
                    rd_diffuse_quadrature_error=np.abs(t_rule / t_exact - 1.0) * diffuse,
                    rd_diffuse_monotone=isotonic(diffuse, se))
    a_red = reduced_albedo(albedo, g)
    measured, measured_se = cols["rho_eff_normal"], cols["rho_eff_normal_stderr"]
    for model, values in (("dipole", dipole_total_rd(a_red, eta)), ("burley", burley_total_rd(a_red))):
        err = values - measured
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(measured_se > 0, err / measured_se, np.nan)
        cols.update({f"{model}_rho_eff": values, f"{model}_error": err, f"{model}_z": z,
                     f"{model}_error_diffuse": values - cols["rd_diffuse"]})
    meta = {
        "estimator": est, "g": g, "eta": eta,
        "diffuse_rule": None if rule is None else {"points": rule[0], "incidence_deg": [angles[k] for k in rule[1]],
                                                   "weights": rule[2].tolist()},
        "diffuse_needs": None if rule is not None else
        f"add the Gauss-Legendre angles, e.g. 4 points: incidence_deg {diffuse_incidence_deg(4)} (and 0)",
        "monotone_adjusted": {c: int(np.sum(np.isfinite(cols[c]) & (cols[c] != cols[c.replace("_monotone", "")])))
                              for c in ("rd_normal_monotone", "rd_diffuse_monotone")},
        "definitions": DEFINITIONS,
        "provenance": source.provenance("albedo-map"),
    }
    return AlbedoMap(est, g, eta, cols, meta)


def _stem(m: AlbedoMap) -> str:
    return f"albedo-map-{m.estimator}-g{m.g:+.4f}-eta{m.eta:.4f}"


def _number(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def write_albedo_map(source: ExportSource, out_dir: str | Path) -> list[str]:
    """Write ``albedo-map-EST-gG-etaE.csv`` and ``.json`` per map into ``out_dir``; the names."""
    out = Path(out_dir)
    names = []
    for m in albedo_maps(source):
        stem = _stem(m)
        with open(out / f"{stem}.csv", "w", newline="", encoding="utf-8") as f:
            writer = csv.writer(f)
            writer.writerow(COLUMNS)
            writer.writerows([repr(float(m.columns[c][i])) for c in COLUMNS] for i in range(len(m.columns["albedo"])))
        doc = {**m.meta, "columns": {c: [_number(x) for x in m.columns[c]] for c in COLUMNS}}
        (out / f"{stem}.json").write_text(json.dumps(doc, indent=1, allow_nan=False) + "\n", encoding="utf-8")
        names += [f"{stem}.csv", f"{stem}.json"]
    return names
