"""`tcspc range --spatial`: generic histograms laid out as an image and ranged with their
neighbours (:mod:`stages.ranging.spatial`, docs/ranging.md "Ranging with the neighbours").

A row's place on the array comes from the file's optional ``row`` and ``col`` columns, or
from ``--geometry`` (its ``tdc`` -> row, col). Every measurement is one image (pixels
the file does not have are empty histograms); reference channels are not ranged. The bins
are the file's nominal ones, the time origin ``--delay-ps``; no pile-up correction (the
histograms are taken as photon counts: a photon-counting sensor, or few photons a cycle).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from scipy.constants import c as C_LIGHT

from pipeline.io.generic import read_generic
from schemas.errors import SchemaMismatch
from schemas.outputs import RANGES
from stages.geometry import Geometry
from stages.ranging.spatial import spatial

#: the ranges columns added by --spatial (the ranges reader keeps extra columns)
EXTRA = ("row", "col")


def _places(path, table: pa.Table, geom: Geometry | None) -> dict[tuple[str, int], tuple]:
    """(measurement, tdc) -> (row, col)."""
    names = table.column("measurement").to_pylist()
    tdc = table.column("tdc").to_pylist()
    if geom is not None:
        idx = geom.index_of(np.asarray(tdc, np.int64))
        return {(m, t): (int(geom.row[i]), int(geom.col[i]))
                for m, t, i in zip(names, tdc, idx, strict=True) if i >= 0}
    if not {"row", "col"} <= set(table.column_names):
        raise SchemaMismatch(f"{path}: --spatial needs the rows' places: columns row and "
                             "col in the file, or --geometry")
    rows, cols = table.column("row").to_pylist(), table.column("col").to_pylist()
    out = {}
    for i, (m, t, r, c) in enumerate(zip(names, tdc, rows, cols, strict=True)):
        if r is None or c is None or r < 0 or c < 0 or r > 65535 or c > 65535:
            raise SchemaMismatch(f"{path}: row {i}: row and col must be integers 0..65535, "
                                 f"found {r}, {c}")
        out[(m, t)] = (int(r), int(c))
    return out


def range_spatial(path: str | Path, delay_s: float, sigma_s: float, p_fa: float,
                  geom: Geometry | None = None, max_returns: int = 2,
                  threads: int = 2) -> tuple[pa.Table, int]:
    """The ranges table of a generic histograms file, and how many non-reference rows
    had no place (not ranged: the caller says so)."""
    table = pq.read_table(path)
    meas = read_generic(path, table)
    places = _places(path, table, geom)
    parts, unplaced = [], 0
    for m in meas:
        use = [i for i, t in enumerate(m.tdc) if not m.reference[i]]
        where = [places.get((m.name, int(m.tdc[i]))) for i in use]
        unplaced += sum(w is None for w in where)
        use, where = ([i for i, w in zip(use, where, strict=True) if w is not None],
                      [w for w in where if w is not None])
        if not use:
            continue
        rc = np.array(where)
        if len(set(map(tuple, rc))) != len(rc):
            raise SchemaMismatch(f"{path}: measurement {m.name!r}: two rows share a row "
                                 "and col")
        h, w = rc.max(0) + 1
        img = np.zeros((h, w, m.counts.shape[1]))
        img[rc[:, 0], rc[:, 1]] = m.counts[use]
        est = spatial(img, m.bin_width_s, sigma_s, p_fa, max_returns=max_returns,
                      t0_s=-delay_s, threads=threads)
        r, c = rc[:, 0], rc[:, 1]
        t = est.t_s[r, c]                                 # (n, k)
        det = est.detected[r, c]
        keep = np.zeros_like(det)
        keep[:, 0] = True                                 # every pixel has a row 0
        keep |= det
        n_i, k_i = np.nonzero(keep)
        dist = t[n_i, k_i] * C_LIGHT / 2
        flag = np.where(np.isfinite(dist), "", "no candidate")
        parts.append(pa.table({
            "measurement": pa.array([m.name] * n_i.size, pa.string()),
            "tdc": pa.array(m.tdc[use][n_i], pa.uint32()),
            "distance_m": dist,
            "sigma_m": est.sigma_s[r, c][n_i, k_i] * C_LIGHT / 2,
            "fwhm_m": np.full(n_i.size, 2.3548200450309493 * sigma_s * C_LIGHT / 2),
            "signal_counts": est.signal_counts[r, c][n_i, k_i],
            "background_per_bin": est.background_per_bin[r, c][n_i, k_i],
            "detected": det[n_i, k_i],
            "estimator": pa.array(["spatial"] * n_i.size, pa.string()),
            "return_index": pa.array(k_i, pa.uint8()),
            "flag": pa.array(flag.tolist(), pa.string()),
            "row": pa.array(r[n_i], pa.uint16()), "col": pa.array(c[n_i], pa.uint16()),
        }, schema=pa.schema(list(RANGES.fields) + [pa.field("row", pa.uint16()),
                                                    pa.field("col", pa.uint16())],
                            metadata=RANGES.schema.metadata)))
    if not parts:
        raise SchemaMismatch(f"{path}: no row to range with --spatial (every row a "
                             "reference channel or without a place)")
    return pa.concat_tables(parts), unplaced
