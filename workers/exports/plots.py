"""The ``plots`` export: matplotlib figures, each as PNG and SVG (needs the ``plot`` extra).

* ``rd-EST-gG-etaE-incI``: Rd(r) on log-log axes, one panel per component (single, multiple,
  total), one series per channel (per albedo for a sweep; at most 6, spread over the albedos),
  with standard-error bars (bins without events are left out) and, at normal incidence, the
  models beside it: photon beam diffusion (pbrt's ``BeamDiffusionSS`` / ``MS``, the single,
  multiple and total panels) and the classical dipole (multiple and total), both per unit
  incident power (times 1 - R_spec) for the channel's sigma_a, sigma_s, g, eta, from the first
  to the last bin centre (also where few bins had events). Points are at the bins' centres
  (geometric for r > 0, half the first edge for the first bin). The y axis holds every point
  and its bars (at most 12 decades); a bar reaching 0, which a log axis cannot show, ends at
  the axis bottom.
* ``s-EST-gG-etaE-incI``: S over the outgoing hemisphere (projected: radius sin theta_o, angle
  phi_o from the outward radial direction) at four radii, for the total component, one row per
  series, all on one colour scale (at most 12 decades); at oblique incidence for the theta_s bin
  holding +x (the incidence plane, forward); not drawn when the bins have a single outgoing
  direction bin.
* ``albedo-map-EST-gG-etaE`` (datasets with two or more albedos at a (g, eta), e.g. sweeps):
  the albedo map of :mod:`.albedo_map` with the dipole's and Christensen-Burley's relations,
  and their error per albedo against the measurement's +- 2 standard-error band, on a
  symmetric-log axis linear within the band (so the band stays visible beside model errors
  many times larger).

SVGs carry no date and fixed element ids, so the same tables give the same files. Each curve of
an Rd figure has a gid (:func:`line_gid`, the id of its SVG group): the measured points, their
error bars (``-stderr``), and the models, so a reader (or a test) can find what was drawn;
:func:`figures` gives the Figure objects themselves.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from schema import COMPONENTS
from workers.models.diffusion import dipole_rd, pbd_multiple, pbd_rd, pbd_single

from .albedo_map import AlbedoMap, albedo_maps
from .grid import table_grid
from .source import ExportError, ExportSource

__all__ = ["write_plots", "figures", "line_gid", "MAX_SERIES"]

MAX_SERIES = 6
"""Most series drawn in one panel (a sweep's albedos are thinned to this many)."""
_RC = {"svg.hashsalt": "bssrdf-db", "font.size": 9, "axes.titlesize": 9}


def _save(fig: Figure, out: Path, stem: str) -> list[str]:
    with matplotlib.rc_context(_RC):
        fig.savefig(out / f"{stem}.png", dpi=130)
        fig.savefig(out / f"{stem}.svg", metadata={"Date": None})
    return [f"{stem}.png", f"{stem}.svg"]


def _groups(grid):
    """(estimator index, g, eta) -> [(medium index, channel index, albedo)] of the series, by albedo,
    thinned to MAX_SERIES."""
    out: dict = {}
    for m in range(len(grid.keys["medium"])):
        for c in range(len(grid.keys["channel"])):
            if np.isfinite(grid.albedo[m, c]):
                out.setdefault((float(grid.g[m, c]), float(grid.eta[m])), []).append((m, c, float(grid.albedo[m, c])))
    for key, series in out.items():
        series.sort(key=lambda s: s[2])
        if len(series) > MAX_SERIES:
            pick = np.unique(np.round(np.linspace(0, len(series) - 1, MAX_SERIES)).astype(int))
            out[key] = [series[i] for i in pick]
    return out


def _centres(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.where(lo > 0, np.sqrt(lo * np.maximum(hi, lo)), 0.5 * hi)


def _label(source: ExportSource, grid, m: int, c: int) -> str:
    if source.spec.is_sweep:
        return f"albedo {grid.albedo[m, c]:.4g}"
    return f"{grid.keys['channel'][c]} (albedo {grid.albedo[m, c]:.4g})"


def line_gid(curve: str, comp: str, grid, m: int, c: int) -> str:
    """The gid (SVG id) of a curve of an Rd figure: ``rd-CURVE-COMP-mM-CHANNEL``, curve one of
    ``measured`` (the data points with their error bars), ``pbd`` (photon beam diffusion) and
    ``dipole`` (the classical dipole), M the medium, CHANNEL the channel name."""
    return f"rd-{curve}-{comp}-m{int(grid.keys['medium'][m])}-{grid.keys['channel'][c]}"


def _rd_range(radial, e, i, series) -> tuple[float, float] | None:
    """(bottom, top) of an Rd figure's y axis: every drawn point and the ends of its error bars
    that a log axis can show (rd - se > 0), with a margin; at most 12 decades."""
    lows, highs = [], []
    for k in range(len(radial.keys["component"])):
        for m, c, _a in series:
            rd, se = radial.values["Rd_r"][e, m, i, c, k], radial.values["Rd_r_stderr"][e, m, i, c, k]
            ok = np.isfinite(se) & (rd > 0)
            lows += [rd[ok], (rd - se)[ok & (rd - se > 0)]]
            highs.append((rd + se)[ok])
    low, high = np.concatenate(lows), np.concatenate(highs)
    if not high.size:
        return None
    top = high.max() * 1.5
    return max(low.min() / 1.5, top * 1e-12), top


def _rd_figure(source, radial, summary, e, i, series, title) -> Figure:
    fig = Figure(figsize=(11, 3.8), layout="constrained")
    axes = fig.subplots(1, 3, sharey=True)
    inc = float(radial.keys["incidence"][i])
    colours = matplotlib.colormaps["viridis"](np.linspace(0, 0.9, len(series)))
    limits = _rd_range(radial, e, i, series)
    bottom = limits[0] if limits else 0.0
    for ax, comp in zip(axes, COMPONENTS):
        k = list(radial.keys["component"]).index(comp)
        for colour, (m, c, _a) in zip(colours, series):
            lo, hi = radial.edges["r"][0][m, c], radial.edges["r"][1][m, c]
            rd, se = radial.values["Rd_r"][e, m, i, c, k], radial.values["Rd_r_stderr"][e, m, i, c, k]
            ok = np.isfinite(se) & (rd > 0) & (rd >= bottom)
            r = _centres(lo, hi)
            low = np.minimum(se, rd - bottom)  # a bar reaching 0 (or below the axis) ends at the axis bottom
            points = ax.errorbar(r[ok], rd[ok], yerr=[low[ok], se[ok]], fmt="o", ms=2.5, lw=0.8, color=colour,
                                 label=_label(source, radial, m, c))
            gid = line_gid("measured", comp, radial, m, c)
            points.lines[0].set_gid(gid)  # the points; their bars get their own id (SVG ids are unique)
            for bars in points.lines[2]:
                bars.set_gid(f"{gid}-stderr")
            if inc == 0.0:  # models over the bins' radii, drawn even where few bins had events
                _models(ax, source, radial, summary, (e, m, i, c), comp, r, colour)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("r [mm]" if not source.spec.is_sweep else "r [mm] = r sigma_t")
        ax.set_title(comp)
        ax.grid(True, which="major", alpha=0.3)
    if limits:  # the measurement and its bars, at most 12 decades (models can fall much further)
        axes[0].set_ylim(*limits)
    axes[0].set_ylabel("Rd(r) [1/mm^2] per unit incident power")
    handles, labels = axes[2].get_legend_handles_labels()
    if inc == 0.0:  # the models' line styles, in black (each series draws them in its colour)
        handles += [Line2D([], [], ls="--", color="k", lw=0.9), Line2D([], [], ls=":", color="k", lw=1.1)]
        labels += ["photon beam diffusion", "classical dipole"]
    fig.legend(handles, labels, loc="outside right center", fontsize=7)  # centred: clear of the suptitle
    fig.suptitle(title + ("  (sweep media have sigma_t = 1/mm: radii are optical)" if source.spec.is_sweep else ""))
    return fig


def _models(ax, source, radial, summary, index, comp, r, colour) -> None:
    """Photon beam diffusion (dashed) and the classical dipole (dotted) for series ``index`` =
    (estimator, medium, incidence, channel) at normal incidence."""
    e, m, i, c = index
    ch = next(x for x in source.spec.medium_spec(int(radial.keys["medium"][m])).channels()
              if x.name == radial.keys["channel"][c])
    k = list(summary.keys["component"]).index("total")
    entered = 1.0 - summary.values["R_spec"][e, m, i, c, k]  # the grids share their key axes
    xs = np.geomspace(r.min(), r.max(), 160)
    sa, ss, g, eta = ch.sigma_a, ch.sigma_s, ch.g, float(radial.eta[m])
    pbd = {"single": pbd_single, "multiple": pbd_multiple, "total": pbd_rd}[comp](xs, sa, ss, g, eta)
    ax.plot(xs, entered * pbd, "--", color=colour, lw=0.9, gid=line_gid("pbd", comp, radial, m, c))
    if comp != "single" and ch.sigma_s_reduced > 0:
        ax.plot(xs, entered * dipole_rd(xs, sa, ch.sigma_s_reduced, eta), ":", color=colour, lw=1.1,
                gid=line_gid("dipole", comp, radial, m, c))


def _s_figure(source, bins, e, i, series, title) -> Figure:
    n_r = bins.values["S"].shape[5]
    picks = np.unique(np.clip(np.round(np.array([0.08, 0.3, 0.55, 0.8]) * (n_r - 1)).astype(int), 0, n_r - 1))
    fig = Figure(figsize=(2.6 * len(picks) + 1.0, 2.5 * len(series) + 0.6), layout="constrained")
    axes = np.atleast_2d(fig.subplots(len(series), len(picks), subplot_kw={"projection": "polar"}, squeeze=False))
    k = list(bins.keys["component"]).index("total")
    cos_lo, cos_hi = bins.edges["cos_theta_o"]
    phi_lo, phi_hi = bins.edges["phi_o"]
    rings = np.sqrt(1.0 - np.concatenate([cos_hi[-1:], cos_lo[::-1]]) ** 2)  # sin(theta_o), increasing
    split = int(np.ceil(72 / len(phi_lo)))  # each phi_o bin drawn as `split` wedges of its one value
    phis = np.linspace(phi_lo[0], phi_hi[-1], len(phi_lo) * split + 1)
    cubes = [bins.values["S"][e, m, i, c, k][:, 0] for m, c, _a in series]  # [r, cos, phi] at theta_s bin 0 (+x)
    shown = np.concatenate([cube[picks].ravel() for cube in cubes])
    positive = shown[np.isfinite(shown) & (shown > 0)]
    norm = None
    if positive.size:  # one colour scale for every row (albedo or channel), at most 12 decades
        top = positive.max() * (1 + 1e-9)
        norm = LogNorm(max(positive.min(), top * 1e-12), top)
    mesh = None
    for row, ((m, c, _a), cube) in enumerate(zip(series, cubes)):
        for col, j in enumerate(picks):
            ax = axes[row, col]
            img = np.repeat(np.where(cube[j] > 0, cube[j], np.nan)[::-1], split, axis=1)  # [sin ring, wedge]
            # rasterized: in the SVG the mesh of wedges is one embedded image (small, fast to write)
            mesh = ax.pcolormesh(phis, rings, img, norm=norm, cmap="magma", shading="flat", rasterized=True)
            lo, hi = bins.edges["r"][0][m, c][j], bins.edges["r"][1][m, c][j]
            ax.set_title(f"r in [{lo:.3g}, {hi:.3g}) mm", fontsize=8)
            ax.set_yticklabels([])
            ax.set_xticks(np.deg2rad([0, 90, 180, 270]), ["out", "90", "in", "270"], fontsize=7)
        axes[row, 0].set_ylabel(_label(source, bins, m, c), labelpad=22)
    fig.colorbar(mesh, ax=axes[:, -1], label="S [1/(mm^2 sr)], one scale for every row", shrink=0.6)
    fig.suptitle(title + "\nprojected outgoing hemisphere: radius sin(theta_o), angle phi_o from the outward radial "
                 "direction; white: no events")
    return fig


def figures(source: ExportSource):
    """Yield (file stem, Figure) for every figure of the export (module docstring)."""
    radial = table_grid(source.tables["radial"], "radial")
    bins = table_grid(source.tables["bins"], "bins")
    summary = table_grid(source.tables["summary"], "summary")
    for (g, eta), series in sorted(_groups(radial).items()):
        for e, est in enumerate(radial.keys["estimator"]):
            for i, inc in enumerate(radial.keys["incidence"]):
                tag = f"{est}-g{g:+.4f}-eta{eta:.4f}-inc{inc:g}"
                title = f"{source.label}: {est}, g = {g:g}, eta = {eta:g}, theta_i = {inc:g} deg"
                yield f"rd-{tag}", _rd_figure(source, radial, summary, e, i, series, title)
                if bins.values["S"].shape[7] * bins.values["S"].shape[8] > 1:  # one direction bin: nothing to show
                    yield f"s-{tag}", _s_figure(source, bins, e, i, series, title)
    try:
        maps = albedo_maps(source)
    except ExportError:
        maps = []  # one albedo per (g, eta), or no normal incidence: there is no map to draw
    for m in maps:
        yield f"albedo-map-{m.estimator}-g{m.g:+.4f}-eta{m.eta:.4f}", _albedo_map_figure(source, m)


def write_plots(source: ExportSource, out_dir: str | Path) -> list[str]:
    """Write the figures (PNG and SVG) into ``out_dir``; the file names."""
    out = Path(out_dir)
    names: list[str] = []
    for stem, fig in figures(source):
        names += _save(fig, out, stem)
    return names


def _albedo_map_figure(source: ExportSource, m: AlbedoMap) -> Figure:
    """Measured rho_eff(albedo) with the models, and the models' error per albedo."""
    c = m.columns
    fig = Figure(figsize=(11, 4), layout="constrained")
    left, right = fig.subplots(1, 2)
    a = c["albedo"]
    left.errorbar(a, c["rho_eff_normal"], yerr=c["rho_eff_normal_stderr"], fmt="o", ms=3, color="k",
                  label="measured, normal incidence: Rd / (1 - R_spec)")
    if np.isfinite(c["rd_diffuse"]).any():
        left.errorbar(a, c["rd_diffuse"], yerr=c["rd_diffuse_stderr"], fmt="s", ms=3, color="tab:green",
                      label="measured, diffuse illumination: Rd (per incident power)")
    left.plot(a, c["dipole_rho_eff"], "-", color="tab:blue", label="classical dipole")
    left.plot(a, c["burley_rho_eff"], "-", color="tab:orange",
              label="Christensen-Burley fit (diffuse light, index-matched)")
    left.set_xlabel("single-scattering albedo sigma_s / sigma_t")
    left.set_ylabel("total diffuse reflectance")
    left.legend(fontsize=7)
    left.grid(True, alpha=0.3)
    band = 2 * c["rho_eff_normal_stderr"]
    right.fill_between(a, -band, band, color="0.85", label="+- 2 standard errors of the measurement")
    right.plot(a, c["dipole_error"], "o-", ms=3, color="tab:blue", label="classical dipole - measured (normal)")
    right.plot(a, c["burley_error"], "o-", ms=3, color="tab:orange", label="Christensen-Burley - measured (normal)")
    if np.isfinite(c["rd_diffuse"]).any():
        right.plot(a, c["burley_error_diffuse"], "s--", ms=3, color="tab:orange",
                   label="Christensen-Burley - measured (diffuse)")
    right.axhline(0, color="k", lw=0.6)
    widest = np.nanmax(band) if np.isfinite(band).any() else 0.0
    if widest > 0:  # linear within the band, logarithmic beyond: the band keeps a visible height
        right.set_yscale("symlog", linthresh=widest, linscale=1.5)
    right.set_xlabel("single-scattering albedo")
    right.set_ylabel("model - measured (per unit power entered)")
    right.legend(fontsize=7)
    right.grid(True, alpha=0.3)
    fig.suptitle(f"{source.label}: albedo map, {m.estimator}, g = {m.g:g}, eta = {m.eta:g}")
    return fig
