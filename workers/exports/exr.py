"""The ``exr`` export: OpenEXR images of S and its standard error (float32, lossless ZIP).

One multi-part file per (estimator, medium, incidence angle): ``LABEL-EST-mM-incI.exr``. Its
parts, named ``CHANNEL.COMPONENT.VIEW``, are two views of the bins' S [1/(mm^2 sr)]:

* view ``r_theta_s``: x = radial bin, y = exit-azimuth bin theta_s; one image per outgoing
  direction bin, EXR channels ``S.c{k}.p{m}`` and ``S_stderr.c{k}.p{m}`` (cos(theta_o) bin k,
  phi_o bin m);
* view ``r_cos_theta_o``: x = radial bin, y = cos(theta_o) bin; EXR channels ``S.t{t}.p{m}``
  and ``S_stderr.t{t}.p{m}`` (theta_s bin t, phi_o bin m).

Every pixel is one stored bin (no bins are combined, so each standard error is the table's;
NaN where a bin had no event). String header attributes: ``bssrdf.provenance`` and
``bssrdf.spec`` (JSON), ``bssrdf.key`` (estimator, medium, incidence, channel, component,
albedo, g, eta), ``bssrdf.units``, ``bssrdf.axes`` (what x, y and the channel names index) and
``bssrdf.edges`` (JSON of the bin edges in float64: r_lo_mm / r_hi_mm, theta_s, cos_theta_o,
phi_o). All parts share the display window of the largest image (an OpenEXR multi-part rule).
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
    each part's attributes under the key ``"__attributes__"``."""
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
                parts = {}
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
                        parts[f"{ch}.{comp}.r_theta_s"] = _view(cube, err, (1, 0, 2, 3), "c", "p", attrs,
                                                               "x: radial bin, y: theta_s bin; S.c{k}.p{m}: cos_theta_o bin k, phi_o bin m")
                        parts[f"{ch}.{comp}.r_cos_theta_o"] = _view(cube, err, (2, 0, 1, 3), "t", "p", attrs,
                                                                   "x: radial bin, y: cos_theta_o bin; S.t{t}.p{m}: theta_s bin t, phi_o bin m")
                files[f"{source.label}-{est}-m{int(medium)}-inc{float(inc):g}.exr"] = parts
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
        height = max(next(iter(_pixels(p).values())).shape[0] for p in parts.values())
        width = max(next(iter(_pixels(p).values())).shape[1] for p in parts.values())
        window = (np.array([0, 0], dtype=np.int32), np.array([width - 1, height - 1], dtype=np.int32))
        exr_parts = [OpenEXR.Part({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
                                   "displayWindow": window, **part["__attributes__"]}, _pixels(part), part_name)
                     for part_name, part in parts.items()]
        with OpenEXR.File(exr_parts) as f:
            f.write(str(Path(out_dir) / name))
        names.append(name)
    return names


def _pixels(part: dict) -> dict[str, np.ndarray]:
    return {k: v for k, v in part.items() if k != "__attributes__"}
