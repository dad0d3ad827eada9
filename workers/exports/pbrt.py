"""The ``pbrt`` export: pbrt's tabulated radial profile, one table per (estimator, g, eta).

What pbrt's ``TabulatedBSSRDF`` samples (workers.tabulated), measured instead of computed by
photon beam diffusion. Rows: the albedos at (g, eta) of the dataset's media and channels
(a sweep's albedo axis; rhoSamples must be distinct). Columns: pbrt's radius nodes, which
requires the radial spacing ``"pbrt"`` (bins centred on the nodes). Each entry is

    profile[i, j] = f_i(r_j),  f = the density in optical radius r sigma_t of the flux leaving
                    per unit power entered at normal incidence: Rd(r) / (1 - R_spec) times
                    2 pi r, exit Fresnel included (pbrt's normalisation of its table),

single plus multiple scattering, from the bin masses by :func:`workers.exports.nodes.node_values`
(bins centred on the nodes, corrected for the local power-law slope, with the estimated error
``profileNodeError``). rhoEff and profileCDF are the Catmull-Rom integrals of the rows, as pbrt
computes them (``IntegrateCatmullRom``), so a pbrt loader that recomputes them gets the same.
Standard errors: ``profileStderr`` from the bins'; ``rhoEffStderr`` of the exit tally is the
standard error of rhoEff itself, the node errors through the integration weights with the bins'
covariance (workers.exports.rho_eff); for estimators whose bins' covariance is not stored it is
that of the measured total Rd / (1 - R_spec), which rhoEff estimates up to the part beyond the
last node and the spline's integration error (< 1e-3 relative on pbrt's nodes,
tests/workers/test_tabulated.py). ``rhoEffStderrMeaning`` says which.

Paths cut at the spec's ``max_scatter`` (albedo 1 has no other end) leave their weight out of
the profile and rhoEff; it is reported per albedo as ``rhoTruncated`` with its standard error.
A row without any exit (albedo 0) is all zeros with NaN standard errors (no events).

As in pbrt's own diffusion tables, the Catmull-Rom spline can dip below 0 where a profile falls
steeply (or to bins without events); pbrt's Pdf_Sr clamps there and its sampler never lands
there, so the two differ by that mass, reported per albedo as ``profileNegativeMass``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from schema.bins import pbrt_radius_nodes
from workers.catmull_rom import integrate_catmull_rom, negative_mass

from .nodes import check_pbrt_edges, node_values
from .pbrt_io import PbrtTable, write_pbrt_binary, write_pbrt_json
from .profiles import radial_profiles, summary_rows
from .rho_eff import DISJOINT_ESTIMATORS, MEANING, disjoint_stderr, rho_eff_coefficients
from .source import ExportError, ExportSource

__all__ = ["pbrt_tables", "write_pbrt", "NORMALISATION"]

NORMALISATION = ("per unit power entered at normal incidence (the stored tables divided by 1 - R_spec), "
                 "exit Fresnel transmission included, single + multiple scattering")
UNITS = {"radiusSamples": "optical radius r sigma_t", "profile": "1 / optical radius (2 pi r Sr, sigma_t = 1)",
         "rhoEff": "dimensionless", "profileCDF": "dimensionless"}
NODE_VALUES = ("bins centred on the nodes in log r (radial spacing 'pbrt'), mass / width corrected by the "
               "local power-law slope b h / sinh(b h); profileNodeError estimates the error this adds "
               "(workers/exports/nodes.py)")


def _file_stem(estimator: str, g: float, eta: float) -> str:
    return f"pbrt-{estimator}-g{g:+.4f}-eta{eta:.4f}"


def pbrt_tables(source: ExportSource) -> list[PbrtTable]:
    """Every (estimator, g, eta) table of the dataset (normal incidence, component total)."""
    spec = source.spec
    if spec.bins.radial.spacing != "pbrt":
        raise ExportError(
            f'the pbrt export needs bins centred on pbrt\'s radius nodes: give "bins": {{"radial": {{"count": 64, '
            f'"spacing": "pbrt"}}}} in the spec; {source.label} has radial spacing {spec.bins.radial.spacing!r}')
    profiles = radial_profiles(source.tables["radial"])
    angles = sorted({key[2] for key in profiles})
    if 0.0 not in angles:
        raise ExportError(f"the pbrt export needs normal incidence (0 in incidence_deg); {source.label} has {angles}")
    summary = summary_rows(source.tables["summary"])
    groups: dict[tuple[str, float, float], list] = {}
    for key, prof in profiles.items():
        est, medium, inc, channel, comp = key
        if inc == 0.0 and comp == "total":
            groups.setdefault((est, prof.g, prof.eta), []).append((prof.albedo, prof, summary[key], source.sigma_t(medium, channel)))
    return [_table(source, est, g, eta, rows) for (est, g, eta), rows in sorted(groups.items())]


def _table(source: ExportSource, estimator: str, g: float, eta: float, rows: list) -> PbrtTable:
    rows.sort(key=lambda row: row[0])
    albedos = [row[0] for row in rows]
    if len(albedos) < 2 or len(set(albedos)) != len(albedos):
        raise ExportError(
            f"a pbrt table needs at least 2 distinct albedos at (g, eta) = ({g}, {eta}); {source.label} has "
            f"{albedos[:8]} ({estimator}): measure a sweep over albedo, e.g. \"sweep\": {{\"albedo\": "
            f"{{\"count\": 100, \"spacing\": \"pbrt\"}}, \"g\": [{g}], \"eta\": [{eta}]}}")
    columns: dict[str, list] = {k: [] for k in ("profile", "stderr", "error", "measured", "measured_se", "beyond", "photons",
                                          "truncated", "truncated_se", "rho_eff_se")}
    radius = pbrt_radius_nodes(len(rows[0][1].r_lo_mm))
    disjoint = estimator in DISJOINT_ESTIMATORS
    for _albedo, prof, summ, sigma_t in rows:
        edges = np.concatenate([prof.r_lo_mm, prof.r_hi_mm[-1:]]) * sigma_t
        if not check_pbrt_edges(edges):
            raise ExportError(f"medium {prof.key[1]} channel {prof.key[3]} of {source.label}: radial edges are not "
                              "pbrt's nodes in optical radii")
        entered = 1.0 - summ["R_spec"]
        m, m_se = prof.masses
        values, se, err = node_values(m / entered, m_se / entered)
        columns["profile"].append(values)
        columns["stderr"].append(se)
        columns["error"].append(err)
        columns["measured"].append(summ["Rd"] / entered)
        columns["measured_se"].append(summ["Rd_stderr"] / entered)
        columns["beyond"].append(summ["Rd_beyond_rmax"] / entered)
        columns["photons"].append(float(summ["photons"]))
        columns["truncated"].append(summ["truncated"] / entered)
        columns["truncated_se"].append(summ["truncated_stderr"] / entered)
        columns["rho_eff_se"].append(
            disjoint_stderr(rho_eff_coefficients(radius, m), m / entered, m_se / entered, int(summ["photons"]))
            if disjoint else summ["Rd_stderr"] / entered)
    profile = np.stack(columns["profile"])
    rho_eff, cdf = integrate_catmull_rom(radius, profile)
    meta = {
        "estimator": estimator,
        "units": UNITS,
        "normalisation": NORMALISATION,
        "nodeValues": NODE_VALUES,
        "rhoEffStderrMeaning": MEANING["disjoint" if disjoint else "total"],
        "rhoEffMonotone": bool(np.all(np.diff(rho_eff) > 0)),
        "provenance": source.provenance("pbrt"),
        "albedoRows": albedo_rows(source, g, eta),
    }
    return PbrtTable(
        g=g, eta=eta, rho_samples=np.array([row[0] for row in rows], dtype=np.float64), radius_samples=radius,
        profile=profile, rho_eff=rho_eff, profile_cdf=cdf, profile_stderr=np.stack(columns["stderr"]),
        rho_eff_stderr=np.array(columns["rho_eff_se"]), profile_node_error=np.stack(columns["error"]),
        rho_eff_measured=np.array(columns["measured"]), rho_eff_measured_stderr=np.array(columns["measured_se"]),
        rho_beyond_rmax=np.array(columns["beyond"]), photons=np.array(columns["photons"]),
        profile_negative_mass=negative_mass(radius, profile), rho_truncated=np.array(columns["truncated"]),
        rho_truncated_stderr=np.array(columns["truncated_se"]), meta=meta,
    )


def albedo_rows(source: ExportSource, g: float, eta: float) -> dict:
    """How the table's albedo rows were walked and what that means for their correlation:
    rows of one shared walk group (workers/reweight.py) come from the same photons."""
    spec = source.spec
    if not spec.is_sweep or spec.walk_mode() == "independent":
        return {"walks": "independent", "correlation": "every albedo row has its own walk: rows are independent"}
    albedos = spec.sweep.albedos()
    media = spec.media()
    groups = [[albedos[k[0] % len(albedos)], albedos[k[-1] % len(albedos)]] for k in spec.walk_groups()
              if media[k[-1]].g[0] == g and media[k[-1]].eta == eta]  # fmt: skip
    return {
        "walks": "shared",
        "groups": groups,
        "correlation": "rows whose albedos lie in one group [first, last] are estimated from the same photons, walked at the "
                       "group's last (largest) albedo and reweighted: their errors are positively correlated (nearly fully "
                       "for neighbours), so an interpolation between two rows of a group is more precise than independent "
                       "errors suggest, and errors of several rows must not be combined as independent; groups are independent",
    }  # fmt: skip


def write_pbrt(source: ExportSource, out_dir: str | Path) -> list[str]:
    """Write ``pbrt-EST-gG-etaE.json`` and ``.bin`` per table into ``out_dir``; the file names."""
    out = Path(out_dir)
    names = []
    for t in pbrt_tables(source):
        stem = _file_stem(t.meta["estimator"], t.g, t.eta)
        write_pbrt_json(t, out / f"{stem}.json")
        write_pbrt_binary(t, out / f"{stem}.bin")
        names += [f"{stem}.json", f"{stem}.bin"]
    return names
