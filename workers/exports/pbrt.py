"""The ``pbrt`` export: pbrt's tabulated radial profile, one table per (estimator, g, eta).

What pbrt's ``TabulatedBSSRDF`` samples (workers.models.tabulated), measured instead of computed by
photon beam diffusion. Rows: the albedos at (g, eta) of the dataset's media and channels
(a sweep's albedo axis; rhoSamples must be distinct). Columns: pbrt's radius nodes, which
requires the radial spacing ``"pbrt"`` (bins centred on the nodes). Each entry is

    profile[i, j] = f_i(r_j),  f = the density in optical radius r sigma_t of the flux leaving
                    per unit power entered at normal incidence: Rd(r) / (1 - R_spec) times
                    2 pi r, exit Fresnel included (pbrt's normalisation of its table),

single plus multiple scattering, from the bin masses by
:func:`workers.exports.conserving.conserving_nodes`: the node values whose Catmull-Rom spline
integrates over every bin to that bin's measured mass (bins centred on the nodes), so rhoEff and
profileCDF, the spline's integrals as pbrt computes them (``IntegrateCatmullRom``; a pbrt loader
that recomputes them gets the same), hold exactly the measured energy:

    rhoEff + rhoBeyondRmax = rhoEffMeasured = Rd / (1 - R_spec)   (to rounding),

rhoBeyondRmax being what leaves beyond the last bin edge plus the last bin's part outside the
last node. ``profileNodeError`` states each node's remaining error as a point value of the
profile (modelled nodes, where bins had no events: their whole value). Standard errors:
``profileStderr`` from the node covariance (the bins' covariance through the linear solve);
``rhoEffStderr`` of the exit tally is the standard error of rhoEff itself, sqrt(W Cov(f) W^T)
with the bins' full covariance (one exit per photon; workers.exports.rho_eff); for estimators
whose bins' covariance is not stored it is that of the measured total Rd / (1 - R_spec), which
rhoEff equals up to rhoBeyondRmax. ``rhoEffStderrMeaning`` says which.

Paths cut at the spec's ``max_scatter`` (albedo 1 has no other end) leave their weight out of
the profile and rhoEff; it is reported per albedo as ``rhoTruncated`` with its standard error.
A row without any exit (albedo 0) is all zeros with NaN standard errors (no events).

Every row's spline is >= 0 (bins that would make it dip are pooled, workers.exports.conserving),
so pbrt's Pdf_Sr and its sampler agree at the albedos of the rows; ``profileNegativeMass`` (0
then) says so per row. Between rows pbrt interpolates the rows with Catmull-Rom weights in rho,
some negative, and the interpolated row can dip where a neighbouring row has much more tail:
there Pdf_Sr clamps, the CDF is not monotone and the sampler misses mass.
``rangeNegativeMass`` reports, per albedo range [rho_i, rho_i+1], the most negative
(negative mass / rhoEff) of the interpolated rows at RANGE_SAMPLES albedos inside it, and
``rangeWorstRho`` where; the metadata ``interpolationWarnings`` lists the ranges beyond
NEGLIGIBLE_NEGATIVE (workers.exports.interpolation).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from schema.bins import pbrt_radius_nodes
from workers.models.catmull_rom import integrate_catmull_rom, negative_mass
from workers.models.tabulated import BSSRDFTable

from .conserving import conserving_nodes
from .interpolation import interpolation_warnings, range_negative_mass
from .nodes import check_pbrt_edges
from .pbrt_io import PbrtTable, write_pbrt_binary, write_pbrt_json
from .profiles import radial_profiles, summary_rows
from .rho_eff import DISJOINT_ESTIMATORS, MEANING
from .source import ExportError, ExportSource

__all__ = ["pbrt_tables", "write_pbrt", "NORMALISATION"]

NORMALISATION = ("per unit power entered at normal incidence (the stored tables divided by 1 - R_spec), "
                 "exit Fresnel transmission included, single + multiple scattering")
UNITS = {"radiusSamples": "optical radius r sigma_t", "profile": "1 / optical radius (2 pi r Sr, sigma_t = 1)",
         "rhoEff": "dimensionless", "profileCDF": "dimensionless"}
NODE_VALUES = ("bins centred on the nodes in log r (radial spacing 'pbrt'); node values solve B f = M: the "
               "Catmull-Rom spline integrates over every bin to its measured mass (rhoEff keeps the measured "
               "energy); bins without events, and bins that would make the spline dip below 0, are pooled with "
               "their outer neighbour (nodes on a straight line between measured ones, a geometric tail with "
               "ratio 1/4 beyond the last bin with events); profileNodeError states each node's error as a point "
               "value of the profile (workers/exports/conserving.py)")


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
        nodes = conserving_nodes(m / entered, m_se / entered, int(summ["photons"]) if disjoint else None)
        columns["profile"].append(nodes.values)
        columns["stderr"].append(nodes.stderr)
        columns["error"].append(nodes.error)
        columns["measured"].append(summ["Rd"] / entered)
        columns["measured_se"].append(summ["Rd_stderr"] / entered)
        columns["beyond"].append(summ["Rd_beyond_rmax"] / entered + nodes.beyond)
        columns["photons"].append(float(summ["photons"]))
        columns["truncated"].append(summ["truncated"] / entered)
        columns["truncated_se"].append(summ["truncated_stderr"] / entered)
        columns["rho_eff_se"].append(nodes.rho_eff_stderr if disjoint else summ["Rd_stderr"] / entered)
    profile = np.stack(columns["profile"])
    rho_eff, cdf = integrate_catmull_rom(radius, profile)
    rho = np.array([row[0] for row in rows], dtype=np.float64)
    bssrdf = BSSRDFTable(rho, radius, profile, rho_eff, cdf)
    range_mass, range_rho = range_negative_mass(bssrdf)
    meta = {
        "estimator": estimator,
        "units": UNITS,
        "normalisation": NORMALISATION,
        "nodeValues": NODE_VALUES,
        "rhoEffStderrMeaning": MEANING["disjoint" if disjoint else "total"],
        "rhoEffMonotone": bool(np.all(np.diff(rho_eff) > 0)),
        "interpolationWarnings": interpolation_warnings(rho, range_mass, range_rho),
        "provenance": source.provenance("pbrt"),
        "albedoRows": albedo_rows(source, g, eta),
    }
    return PbrtTable(
        g=g, eta=eta, rho_samples=rho, radius_samples=radius,
        profile=profile, rho_eff=rho_eff, profile_cdf=cdf, profile_stderr=np.stack(columns["stderr"]),
        rho_eff_stderr=np.array(columns["rho_eff_se"]), profile_node_error=np.stack(columns["error"]),
        rho_eff_measured=np.array(columns["measured"]), rho_eff_measured_stderr=np.array(columns["measured_se"]),
        rho_beyond_rmax=np.array(columns["beyond"]), photons=np.array(columns["photons"]),
        profile_negative_mass=negative_mass(radius, profile), rho_truncated=np.array(columns["truncated"]),
        rho_truncated_stderr=np.array(columns["truncated_se"]), range_negative_mass=range_mass,
        range_worst_rho=range_rho, meta=meta,
    )


def albedo_rows(source: ExportSource, g: float, eta: float) -> dict:
    """How the table's albedo rows were walked and what that means for their correlation:
    rows of one shared walk group (workers/fold/reweight.py) come from the same photons."""
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
