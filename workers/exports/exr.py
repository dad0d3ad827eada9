"""The ``exr`` export: OpenEXR images of S and its standard error (float32, lossless ZIP).

One multi-part file per (estimator, medium, incidence angle, view):
``LABEL-EST-mM-incI-VIEW.exr``. Its parts, named ``CHANNEL.COMPONENT`` (CHANNEL the spectral
channel, e.g. ``R`` or ``c0``), hold one view of the bins' S [1/(mm^2 sr)]:

* view ``r_theta_s``: x = radial bin, y = exit-azimuth bin theta_s; one image per outgoing
  direction bin, EXR channels ``S.cos{k}.phi{m}`` and ``S_stderr.cos{k}.phi{m}`` (cos(theta_o)
  bin k, phi_o bin m);
* view ``r_cos_theta_o``: x = radial bin, y = cos(theta_o) bin; EXR channels
  ``S.thetas{t}.phi{m}`` and ``S_stderr.thetas{t}.phi{m}`` (theta_s bin t, phi_o bin m).

The bin axes are spelled out (``cos``, ``thetas``, ``phi``) so that no EXR channel name can be
read as a spectral channel (``c0`` is the default name of a medium's first channel).

Every pixel is one stored bin (no bins are combined, so each standard error is the table's;
NaN where a bin had no event). String header attributes: ``bssrdf.provenance`` and
``bssrdf.spec`` (JSON), ``bssrdf.key`` (estimator, medium, incidence, channel, component,
albedo, g, eta), ``bssrdf.units``, ``bssrdf.axes`` (what x, y and the channel names index) and
``bssrdf.edges`` (JSON of the bin edges in float64: r_lo_mm / r_hi_mm, theta_s, cos_theta_o,
phi_o). Every part of a file has the same image size, and its data window is the display
window (OpenEXR makes the parts of one file share the display window; the two views differ in
height, so they are two files).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import OpenEXR

from .grid import table_grid
from .source import ExportSource

__all__ = ["write_exr", "exr_images", "VIEWS"]

VIEWS = ("r_theta_s", "r_cos_theta_o")
_UNITS = "S and S_stderr: 1/(mm^2 sr), per unit incident power (entry Fresnel factor included); radii in mm"


def exr_images(source: ExportSource) -> dict[str, dict[str, dict[str, np.ndarray]]]:
    """file name -> part name -> EXR channel -> float32 image [y, x] (module docstring), plus
    each part's attributes under the key ``"__attributes__"``; every part of a file has the
    same image size."""
    grid = table_grid(source.tables["bins"], "bins")
    s, s_se = grid.values["S"], grid.values["S_stderr"]
    keys = grid.keys
    r_lo, r_hi = grid.edges["r"]
    spec_json = source.spec.canonical_json()
    provenance = source.provenance_json("exr")
    files: dict[str, dict] = {}
    for e, est in enumerate(keys["estimator"]):
        for m, medium in enumerate(keys["medium"]):
            for i, inc in enumerate(keys["incidence"]):
                parts: dict[str, dict] = {view: {} for view in VIEWS}
                for c, ch in enumerate(keys["channel"]):
                    for k, comp in enumerate(keys["component"]):
                        cube, err = s[e, m, i, c, k], s_se[e, m, i, c, k]  # [r, theta_s, cos, phi]
                        if np.all(np.isnan(cube)):
                            continue  # this medium has no such channel
                        attrs = {
                            "bssrdf.provenance": provenance, "bssrdf.spec": spec_json, "bssrdf.units": _UNITS,
                            "bssrdf.key": json.dumps({"estimator": str(est), "medium": int(medium), "incidence_deg": float(inc),
                                                      "channel": str(ch), "component": str(comp),
                                                      "albedo": float(grid.albedo[m, c]), "g": float(grid.g[m, c]),
                                                      "eta": float(grid.eta[m])}, sort_keys=True),
                            "bssrdf.edges": json.dumps({"r_lo_mm": r_lo[m, c].tolist(), "r_hi_mm": r_hi[m, c].tolist(),
                                                        **{f"{a}_{side}": grid.edges[a][j].tolist()
                                                           for a in ("theta_s", "cos_theta_o", "phi_o")
                                                           for j, side in enumerate(("lo", "hi"))}}),
                        }
                        parts["r_theta_s"][f"{ch}.{comp}"] = _view(
                            cube, err, (1, 0, 2, 3), "cos", "phi", attrs,
                            "x: radial bin, y: theta_s bin; S.cos{k}.phi{m}: cos_theta_o bin k, phi_o bin m")
                        parts["r_cos_theta_o"][f"{ch}.{comp}"] = _view(
                            cube, err, (2, 0, 1, 3), "thetas", "phi", attrs,
                            "x: radial bin, y: cos_theta_o bin; S.thetas{t}.phi{m}: theta_s bin t, phi_o bin m")
                for view in (v for v in VIEWS if parts[v]):
                    files[f"{source.label}-{est}-m{int(medium)}-inc{float(inc):g}-{view}.exr"] = parts[view]
    return files


def _view(cube, err, order, a, b, attrs, axes) -> dict:
    """Images [y, x] of S and S_stderr with the cube transposed to (y, x, a, b)."""
    s, e = np.transpose(cube, order), np.transpose(err, order)
    channels = {}
    for j in range(s.shape[2]):
        for k in range(s.shape[3]):
            channels[f"S.{a}{j}.{b}{k}"] = np.ascontiguousarray(s[:, :, j, k], dtype=np.float32)
            channels[f"S_stderr.{a}{j}.{b}{k}"] = np.ascontiguousarray(e[:, :, j, k], dtype=np.float32)
    return {**channels, "__attributes__": {**attrs, "bssrdf.axes": axes}}


def write_exr(source: ExportSource, out_dir: str | Path) -> list[str]:
    """Write the EXR files into ``out_dir``; the file names."""
    names = []
    for name, parts in exr_images(source).items():
        (height, width), = {image.shape for p in parts.values() for image in _pixels(p).values()}
        window = (np.array([0, 0], dtype=np.int32), np.array([width - 1, height - 1], dtype=np.int32))
        exr_parts = [OpenEXR.Part({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                                   "displayWindow": window, "dataWindow": window, **part["__attributes__"]},
                                  _pixels(part), part_name)
                     for part_name, part in parts.items()]
        with OpenEXR.File(exr_parts) as f:
            f.write(str(Path(out_dir) / name))
        names.append(name)
    return names


def _pixels(part: dict) -> dict[str, np.ndarray]:
    return {k: v for k, v in part.items() if k != "__attributes__"}
