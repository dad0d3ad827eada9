"""npz, csv and exr exports (workers.exports): each read back with its own reader (numpy, csv,
the OpenEXR library) equals the Parquet tables it came from, NaN standard errors included, and
records its provenance."""

from __future__ import annotations

import dataclasses
import json
import re

import numpy as np
import OpenEXR
import pyarrow as pa
import pyarrow.compute as pc
import pytest

from schema import parse_spec
from workers.exports import MANIFEST, write_export
from workers.exports.arrays import read_csv, read_npz
from workers.exports.grid import table_grid
from workers.exports.source import ExportSource

def _with_nan(table: pa.Table, column: str) -> pa.Table:
    """Every third value of ``column`` made NaN: the unresolved bins of the tables' contract."""
    values = table.column(column).to_numpy().copy()
    values[::3] = np.nan
    return table.set_column(table.schema.get_field_index(column), table.schema.field(column), pa.array(values))


@pytest.fixture(scope="module")
def source(arrays_source) -> ExportSource:
    """The shared dataset with NaN standard errors in some bins (unresolved bins)."""
    src = arrays_source
    tables = dict(src.tables, radial=_with_nan(src.tables["radial"], "Rd_r_stderr"),
                  bins=_with_nan(src.tables["bins"], "S_stderr"))
    return dataclasses.replace(src, tables=tables)


def _check_manifest(out, names, source, fmt):
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest["format"] == fmt and manifest["dataset"] == "arrays" and manifest["spec_hash"] == source.spec_hash
    assert set(manifest["files"]) == set(names) - {MANIFEST}
    assert manifest["tables_sha256"] == source.tables_sha256 and manifest["code_version"]["package"]


def test_npz_round_trip(source, tmp_path):
    names = write_export("npz", source, tmp_path)
    _check_manifest(tmp_path, names, source, "npz")
    arrays, meta = read_npz(tmp_path / "arrays.npz")
    assert meta["provenance"]["format"] == "npz" and "1/(mm^2 sr)" in meta["units"]["S"]
    assert meta["axes"]["bins/S"] == ["estimator", "medium", "incidence", "channel", "component", "r", "theta_s",
                                      "cos_theta_o", "phi_o"]
    assert arrays["bins/S"].shape == (2, 1, 2, 2, 3, 6, 3, 2, 2)
    assert list(arrays["estimator"]) == ["connections", "exits"] and list(arrays["channel"]) == ["R", "G"]
    np.testing.assert_array_equal(arrays["incidence_deg"], [0.0, 45.0])
    for table in ("radial", "bins", "summary"):
        t = source.tables[table].to_pylist()
        e = {v: i for i, v in enumerate(arrays["estimator"])}
        c = {v: i for i, v in enumerate(arrays["channel"])}
        k = {v: i for i, v in enumerate(arrays["component"])}
        inc = {v: i for i, v in enumerate(arrays["incidence_deg"])}
        counters: dict = {}
        for row in t:  # the n-th row of a key is its n-th bin, r-major
            key = (e[row["estimator"]], row["medium"], inc[row["incidence_deg"]], c[row["channel"]], k[row["component"]])
            n = counters[key] = counters.get(key, -1) + 1
            for col in meta["axes"]:
                if col.startswith(f"{table}/"):
                    a = arrays[col]
                    idx = key + np.unravel_index(n, a.shape[5:]) if a.ndim > 5 else key
                    assert np.array_equal(a[idx], row[col.split("/")[1]], equal_nan=True), (col, key, n)
    r_lo = arrays["r_lo_mm"][0, 1]
    np.testing.assert_array_equal(r_lo, np.linspace(0, 3, 7)[:-1])
    np.testing.assert_array_equal(arrays["albedo"][0], [0.9, 0.95])
    assert np.isnan(arrays["radial/Rd_r_stderr"]).any()


def test_csv_round_trip(source, tmp_path):
    names = write_export("csv", source, tmp_path)
    _check_manifest(tmp_path, names, source, "csv")
    columns = [line.split(",")[:3] for line in (tmp_path / "columns.csv").read_text().splitlines()[1:]]
    for table in ("radial", "bins", "summary"):
        types = {c: t for f, c, t in columns if f == f"{table}.csv"}
        back = read_csv(tmp_path / f"{table}.csv", types)
        expected = source.tables[table].to_pydict()
        assert list(back) == list(expected)
        for col in expected:
            assert np.array_equal(np.array(back[col]), np.array(expected[col]), equal_nan=True) if types[col] == "double" \
                else back[col] == expected[col], col
    assert "[1/mm^2]" in (tmp_path / "columns.csv").read_text()


def _exr_channels(view: str) -> set[str]:
    """The exact EXR channel names of a part of ``view`` (bins: 6 r x 3 theta_s x 2 cos_theta_o x 2 phi_o)."""
    a, n_a = ("cos", 2) if view == "r_theta_s" else ("thetas", 3)
    return {f"{q}.{a}{j}.phi{m}" for q in ("S", "S_stderr") for j in range(n_a) for m in range(2)}


def test_exr_read_back_with_openexr_equals_parquet(source, tmp_path):
    """Every part holds exactly its channels and header attributes, its data window is the file's
    display window (one view per file), and every pixel of S and of S_stderr equals its Parquet
    bin (each bin seen once per view, NaN standard errors included)."""
    names = write_export("exr", source, tmp_path)
    _check_manifest(tmp_path, names, source, "exr")
    exr = sorted(n for n in names if n.endswith(".exr"))
    assert exr == sorted(f"arrays-{e}-m0-inc{i}-{v}.exr" for e in ("connections", "exits") for i in ("0", "45")
                         for v in ("r_theta_s", "r_cos_theta_o"))
    bins = source.tables["bins"]
    albedo, g = {"R": 0.9, "G": 0.95}, {"R": 0.0, "G": 0.7}
    for name in exr:
        est, inc, view = name.split("-")[1], float(name.split("-inc")[1].split("-")[0]), name[:-4].split("-")[-1]
        with OpenEXR.File(str(tmp_path / name), separate_channels=True) as f:
            parts = {p.name(): p for p in f.parts}
            assert set(parts) == {f"{ch}.{comp}" for ch in ("R", "G") for comp in ("single", "multiple", "total")}
            for part_name, part in parts.items():
                ch, comp = part_name.split(".")
                assert set(part.channels) == _exr_channels(view), part_name
                # no channel-name token reads as a spectral channel ("c0" is a medium's default first channel)
                assert not any(re.fullmatch(r"c\d+", tok) for chan in part.channels for tok in chan.split("."))
                header = part.header
                height = 3 if view == "r_theta_s" else 2  # theta_s or cos_theta_o bins; x: 6 radial bins
                for window in ("dataWindow", "displayWindow"):
                    np.testing.assert_array_equal(np.concatenate(header[window]), [0, 0, 5, height - 1], err_msg=window)
                assert {"bssrdf.provenance", "bssrdf.spec", "bssrdf.key", "bssrdf.units", "bssrdf.axes",
                        "bssrdf.edges"} <= set(header), part_name
                key = json.loads(header["bssrdf.key"])
                assert key == {"estimator": est, "medium": 0, "incidence_deg": inc, "channel": ch, "component": comp,
                               "albedo": pytest.approx(albedo[ch]), "g": g[ch], "eta": 1.4}
                assert json.loads(header["bssrdf.provenance"]) == source.provenance("exr")
                assert parse_spec(header["bssrdf.spec"]).spec_hash() == source.spec_hash
                assert header["bssrdf.spec"] == source.spec.canonical_json()
                assert header["bssrdf.units"].startswith("S and S_stderr: 1/(mm^2 sr), per unit incident power")
                y_axis = "theta_s" if view == "r_theta_s" else "cos_theta_o"
                assert header["bssrdf.axes"].startswith(f"x: radial bin, y: {y_axis}")
                rows = bins.filter(pc.and_(pc.and_(pc.equal(bins["estimator"], est), pc.equal(bins["incidence_deg"], inc)),
                                           pc.and_(pc.equal(bins["channel"], ch), pc.equal(bins["component"], comp))))
                for col in ("S", "S_stderr"):
                    cube = rows.column(col).to_numpy().reshape(6, 3, 2, 2)  # r, theta_s, cos, phi
                    seen = np.zeros(cube.shape, dtype=int)
                    for chan, pix in part.channels.items():
                        if chan.split(".")[0] != col:
                            continue
                        a, b = (int(x.lstrip("abcdefghijklmnopqrstuvwxyz")) for x in chan.split(".")[1:])
                        want = cube[:, :, a, b].T if view == "r_theta_s" else cube[:, a, :, b].T
                        assert pix.pixels.dtype == np.float32
                        np.testing.assert_array_equal(pix.pixels, want.astype(np.float32), err_msg=f"{name} {part_name} {chan}")
                        if view == "r_theta_s":
                            seen[:, :, a, b] += 1
                        else:
                            seen[:, a, :, b] += 1
                    assert np.all(seen == 1), (name, part_name, col)  # every bin is one pixel of this view
                edges = json.loads(header["bssrdf.edges"])
                np.testing.assert_array_equal(edges["r_lo_mm"], np.linspace(0, 3, 7)[:-1])
                np.testing.assert_array_equal(edges["r_hi_mm"], np.linspace(0, 3, 7)[1:])
                np.testing.assert_allclose(edges["cos_theta_o_lo"], [0.0, 0.5])
    assert np.isnan(source.tables["bins"].column("S_stderr").to_numpy()).any()  # the NaN bins were compared


def test_grid_of_summary_has_every_key(source):
    grid = table_grid(source.tables["summary"], "summary")
    assert grid.values["Rd"].shape == (2, 1, 2, 2, 3)
    assert not np.isnan(grid.values["Rd"]).any()
