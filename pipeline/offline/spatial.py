"""`tcspc range --spatial`: generic histograms laid out as an image and ranged with their
neighbours (:mod:`stages.ranging.spatial`, docs/ranging.md "Ranging with the neighbours").

A row's place on the array comes from the file's optional ``row`` and ``col`` columns, or
from ``--geometry`` (its ``tdc`` -> row, col). Every measurement is one image (pixels
the file does not have are empty histograms); reference channels are not ranged. The bins
are the file's nominal ones, the time origin ``--delay-ps``; no pile-up correction (the
histograms are taken as photon counts: a photon-counting sensor, or few photons a cycle).
"""

from __future__ import annotations

from dataclasses import dataclass
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
#: the flag of a pixel whose histogram holds no photon (never detected)
NO_PHOTON = "no photon in its histogram: not detected; the candidate is its neighbours'"


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
                  threads: int = 2, delay_sd_s: float = 0.0, response=None,
                  frames: list | None = None) -> tuple[pa.Table, int]:
    """The ranges table of a generic histograms file, and how many non-reference rows
    had no place (not ranged: the caller says so). ``delay_sd_s``: the delay's own
    standard error (a measured one's), in every sigma in quadrature. ``response``: the
    instrument's measured response (stages.ranging.spatial.SpatialResponse), given to the
    estimator. ``frames``: where given, each measurement's image, estimate and bin width
    are appended to it."""
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
        try:
            est = spatial(img, m.bin_width_s, sigma_s, p_fa, max_returns=max_returns,
                          t0_s=-delay_s, threads=threads, response=response)
        except ValueError as exc:
            raise SchemaMismatch(f"{path}: measurement {m.name!r}: {exc}") from exc
        if frames is not None:
            frames.append((img, est, m.bin_width_s))
        r, c = rc[:, 0], rc[:, 1]
        t = est.t_s[r, c]                                 # (n, k)
        det = est.detected[r, c]
        keep = np.zeros_like(det)
        keep[:, 0] = True                                 # every pixel has a row 0
        keep |= det
        n_i, k_i = np.nonzero(keep)
        dist = t[n_i, k_i] * C_LIGHT / 2
        flag = np.where(np.isfinite(dist), "", "no candidate")
        # a pixel without a photon reports, not detected, a candidate of its neighbours'
        # (their plane, signal and spread; a TMF8820 zone of 0 counts: 1.07 m, sigma 41 m):
        # said in its row, as the per-pixel estimators flag their empty windows
        flag = np.where((m.counts[use].sum(1) == 0)[n_i] & ~det[n_i, k_i],
                        np.where(flag == "", NO_PHOTON, flag + "; " + NO_PHOTON), flag)
        parts.append(pa.table({
            "measurement": pa.array([m.name] * n_i.size, pa.string()),
            "tdc": pa.array(m.tdc[use][n_i], pa.uint32()),
            "distance_m": dist,
            "sigma_m": np.hypot(est.sigma_s[r, c][n_i, k_i], delay_sd_s) * C_LIGHT / 2,
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


def zero_delay_spatial(path: str | Path, sigma_s: float, p_fa: float,
                       geom: Geometry | None = None, threads: int = 2
                       ) -> tuple[float, float, int, object]:
    """The delay (s) that `range --spatial --zero` takes: a zero-distance file (a target
    at the zero in every pixel) ranged with the neighbours from the histograms' start,
    the median of its detected first returns' times. The same estimator then times the
    captures, so its own offset under a response that is not its Gaussian (a tail pulls
    its time 4-6 mm late: docs/ranging.md "A response's tail is not a second surface")
    cancels. Returns the delay, its standard error, and n, the detected pixels; none
    detected is refused. The error is the median's, 1.253 x the times' robust sd over
    the root of the independent pixels: a pixel's time is a fit over its window's
    neighbours, so n over the window's pixels (at least 1), not n. Also the instrument's
    response behind a return, measured on the same frames (the largest measurement's;
    stages.ranging.spatial.measure_response), which the captures' ranging then expects
    behind each return: the fourth of the returns."""
    from stages.ranging.spatial import measure_response

    frames: list = []
    table, _ = range_spatial(path, 0.0, sigma_s, p_fa, geom, max_returns=1, threads=threads,
                             frames=frames)
    det = table.column("detected").to_numpy(zero_copy_only=False)
    t = 2 * table.column("distance_m").to_numpy()[det] / C_LIGHT
    t = t[np.isfinite(t)]
    if not t.size:
        raise SchemaMismatch(f"{path}: no pixel of the zero-distance file detected with "
                             "the neighbours: no delay to measure")
    med = float(np.median(t))
    sd = 1.4826 * float(np.median(np.abs(t - med)))
    from stages.ranging.spatial import WINDOW

    n_eff = max(t.size / (2 * WINDOW + 1) ** 2, 1.0)
    img, est, bin_s = max(frames, key=lambda f: int(f[1].detected[..., 0].sum()))
    return med, 1.253 * sd / np.sqrt(n_eff), int(t.size), measure_response(img, est, bin_s)


#: the common time axis's bin, a fraction of the chip's median LSB (docs/ranging.md
#: "On the chip"): 2 bins a code, so that a code's counts, spread evenly over its own ps
#: interval, land on the common bins with little added quantisation
SUBBINS = 2
#: the flags of a chip's TDC the spatial ranging leaves out (a row each, not detected)
UNPLACED = "no pixel in the geometry: not ranged (spatial)"
NO_DELAY = "no delay: not ranged (spatial)"
#: the flag of a TDC whose worker's part of the measurement did not arrive (:class:`FrameGather`)
MISSING = "its worker's part of the measurement did not arrive: not ranged (spatial)"


def common_axis(edges_s: np.ndarray, counts: np.ndarray, valid: np.ndarray,
                use: np.ndarray, bin_s: float) -> tuple[np.ndarray, float]:
    """Each used row's histogram on one time axis.

    ``edges_s`` (n, codes + 1) each row's own bin edges (increasing, seconds, already on a
    shared origin), ``counts`` (n, codes), ``valid`` (n, codes) the codes each row may use
    (contiguous), ``use`` (n,) bool. The axis runs over the times every used row's valid
    codes cover, in bins of ``bin_s``; a code's counts are spread evenly over its own
    interval (the density the code-density test measured it by) and each common bin takes
    the share of every code its interval overlaps: the rows' cumulative counts, linear
    within a code, read at the common edges (one ``np.interp`` for all rows). Returns
    (n_used, bins) counts and the axis's first edge (s)."""
    e = np.asarray(edges_s, np.float64)[use]
    v = np.asarray(valid, bool)[use]
    k = np.arange(v.shape[1])
    first = np.where(v, k, v.shape[1]).min(1)
    last = np.where(v, k, -1).max(1) + 1
    if e.shape[0] == 0 or np.any(last <= first):
        raise ValueError("spatial ranging: a TDC has no valid code on its time axis")
    rows = np.arange(e.shape[0])
    lo = float(np.max(e[rows, first]))
    hi = float(np.min(e[rows, last]))
    nb = int(np.floor((hi - lo) / bin_s))
    if nb < 3:
        raise ValueError(f"spatial ranging: the TDCs' time axes share {max(hi - lo, 0) * 1e9:.3g}"
                         " ns, fewer than 3 bins")
    c = np.where(v, np.asarray(counts, np.float64)[use], 0.0)
    cum = np.zeros(e.shape)
    np.cumsum(c, axis=1, out=cum[:, 1:])
    # strictly increasing (a code of no width, a missing code, keeps its counts in the
    # bin that holds its edge), and every row's edges shifted past the previous row's:
    # one monotone array, one interp
    e = e + np.arange(e.shape[1]) * (1e-9 * bin_s)
    span = float(np.nanmax(e) - np.nanmin(e)) + 4 * bin_s
    off = (rows * span)[:, None]
    grid = lo + bin_s * np.arange(nb + 1)
    at = np.interp((grid[None, :] + off).ravel(), (e + off).ravel(),
                   cum.ravel()).reshape(e.shape[0], nb + 1)
    return np.maximum(np.diff(at, axis=1), 0.0), lo


def range_state_spatial(state, calibration, window_s: float, t_laser_win_s: float,
                        geom: Geometry, sigma_s: float | None = None, p_fa: float = 1e-3,
                        max_returns: int = 2, threads: int = 1,
                        absent: np.ndarray | None = None):
    """:func:`pipeline.offline.ranging.range_state` with the neighbours: a chip's
    measurement (each TDC on its own INL time axis) laid out as ``geom``'s image and ranged
    by :func:`stages.ranging.spatial.spatial` (docs/ranging.md "On the chip").

    Each TDC's codes become arrival times on its calibrated axis (INL, the LSB at this
    light), minus its own delay (eq. 5.3), so that one time means one distance on every
    pixel; its Coates-corrected counts go onto one axis (:func:`common_axis`). The
    response is the calibration's (measured at the delay) unless ``sigma_s``. Returns
    (estimate, distances (m), sigmas (m), note) as ``range_state`` does: a row per TDC
    (return 0) and one per further detected return; a TDC the geometry has no pixel for,
    or without a delay, has one row, not detected, flagged; so has an ``absent`` one (bool a
    TDC: its part of the measurement did not arrive; its rows only keep the light level)."""
    import dataclasses

    from scipy.constants import c as c_light

    from pipeline.offline import ranging as rg
    from stages import calibration as cal
    from stages.ranging import Estimate, Histograms, response_from_data

    calib, axis = rg.calibrated_axis(state, calibration, window_s)
    h = Histograms.from_codes(state.hits, axis.tau_edges_s, state.cycles, window_s,
                              x_t=axis.x_t)
    notes = [axis.note] if axis.note else []
    if sigma_s is None:
        sigma_s = calib.irf_sigma_s
    if not sigma_s:
        sigma_s, how = response_from_data(h)
        notes.append(f"instrument response sigma {sigma_s * 1e12:.1f} ps {how}")
    n = state.n_tdc
    delay = np.asarray(calib.delay_s, np.float64)
    idx = geom.index_of(state.tdc_offset + np.arange(n))
    edges = h.edges_s - delay[:, None]          # arrival time less the pixel's delay
    use = (idx >= 0) & np.isfinite(delay) & np.all(np.isfinite(edges), axis=1)
    if absent is not None:
        use &= ~np.asarray(absent, bool)
    pix = np.flatnonzero(use)
    k = max_returns
    if pix.size:
        bin_s = h.bin_s / SUBBINS
        counts = h.intensity() * h.cycles[:, None]  # Coates: photons, not first photons
        common, lo = common_axis(edges, counts, h.valid, use, bin_s)
        rc = np.stack([np.asarray(geom.row)[idx[pix]], np.asarray(geom.col)[idx[pix]]], 1)
        hh, ww = rc.max(0) + 1
        if absent is not None:  # the image as large as with every part (the same edges)
            placed = idx[(idx >= 0) & np.asarray(absent, bool)]
            hh = max(hh, int(np.max(np.asarray(geom.row)[placed], initial=-1)) + 1)
            ww = max(ww, int(np.max(np.asarray(geom.col)[placed], initial=-1)) + 1)
        img = np.zeros((hh, ww, common.shape[1]))
        img[rc[:, 0], rc[:, 1]] = common
        s = spatial(img, bin_s, sigma_s, p_fa, max_returns=k, t0_s=lo, threads=threads)
    else:  # no TDC to range (none placed, or none with a delay): every row flagged
        s = None
        rc = np.zeros((0, 2), np.int64)
    r, c = rc[:, 0], rc[:, 1]
    rows = np.zeros((n, k), bool)
    rows[:, 0] = True
    det = np.zeros((n, k), bool)
    if s is not None:
        det[pix] = s.detected[r, c]
    rows |= det
    p_i, k_i = np.nonzero(rows)

    def per_tdc(name, fill):
        out = np.full((n, k), fill, np.float64)
        if s is not None:
            out[pix] = getattr(s, name)[r, c]
        return out[p_i, k_i]

    flag = np.full(n, "", dtype=object)
    flag[~np.isfinite(delay)] = NO_DELAY
    flag[idx < 0] = UNPLACED
    if absent is not None:
        flag[np.asarray(absent, bool)] = MISSING
    t_u = per_tdc("t_s", np.nan)
    est = Estimate(t_s=t_u + delay[p_i], sigma_s=per_tdc("sigma_s", np.nan),
                   fwhm_s=np.full(p_i.size, 2.3548200450309493 * sigma_s),
                   signal_counts=per_tdc("signal_counts", 0.0),
                   background_per_bin=per_tdc("background_per_bin", 0.0),
                   detected=det[p_i, k_i], estimator="spatial", flag=flag[p_i],
                   return_index=k_i.astype(np.int64), pixel=p_i)
    with np.errstate(invalid="ignore"):
        distance = cal.distance_m(t_laser_win_s, delay[p_i], window_s - est.t_s)
    est = dataclasses.replace(est, detected=est.detected & np.isfinite(distance))
    est, distance = rg.behind_zero(est, distance)
    cal_s = rg.calibration_sigma_s(calibration, calib, state, axis, est, window_s)
    sig = np.asarray(est.sigma_s, np.float64)
    sig = np.where(np.isfinite(cal_s), np.hypot(sig, cal_s), sig)
    return est, distance, sig * c_light / 2, "; ".join(notes)


# ------------------------------------------------------------------ the daemon's fan-out
#: measurements whose parts the range stage holds while they gather, by default
#: (``[range] hold``): each a chip's frame, <= 128 TDCs x 512 codes x 8 bytes (0.5 MB)
HOLD = 8
#: measurements gathered whole that are remembered, so that a part sent again (a worker
#: restarted between sending and checkpointing) is known as one and not ranged alone
REMEMBER = 64


@dataclass(frozen=True)
class Frame:
    """One measurement's parts gathered: ``state`` every TDC of the frame, [0, n_tdc_total)
    (a missing part's rows the mean of the arrived rows: the light level the time axis is
    read at stays the arrived TDCs'), ``header`` the first part's with the frame's
    ``tdc_range``, ``parts`` each arrived part's (header, (first, end)) by TDC, ``missing``
    the TDC ranges whose part did not arrive."""

    header: dict
    state: object
    parts: list
    missing: list

    @property
    def absent(self) -> np.ndarray | None:
        """Bool per TDC of the frame: its part did not arrive (None: none missing)."""
        if not self.missing:
            return None
        out = np.zeros(self.state.n_tdc, bool)
        for a, b in self.missing:
            out[a - self.state.tdc_offset:b - self.state.tdc_offset] = True
        return out


class FrameGather:
    """The range stage's join of a fan-out by TDC range (``[range] spatial`` with several
    histogram workers): each worker sends its TDC range of a measurement (``tdc_range`` of
    ``n_tdc_total``); the parts of one measurement (its ``measurement`` name) are held until
    they cover every TDC, then given back as one :class:`Frame`. At most ``hold``
    measurements are held: past that the oldest (by ``measurement_index``) is given back
    with what arrived, and so is every held one at the stream's end (:meth:`flush`); those
    are counted in ``incomplete``. A part of a measurement given back whole a moment ago,
    the same again (its words and ``partial``), is a restarted worker's repeat: counted in
    ``duplicates``, not gathered again. A later part of a measurement given back
    incomplete starts a new gathering (it is ranged with what comes with it)."""

    def __init__(self, hold: int = HOLD, remember: int = REMEMBER, n_tdc: int | None = None):
        if hold < 1:
            raise ValueError(f"hold must be >= 1, found {hold}")
        self.hold, self.remember = hold, remember
        self.n_tdc = n_tdc  #: the frame's TDCs where a header has no n_tdc_total
        self._open: dict[str, dict[tuple[int, int], tuple[dict, pa.RecordBatch]]] = {}
        self._done: dict[str, dict[tuple[int, int], tuple]] = {}  # (insertion ordered)
        self.incomplete = 0  #: frames given back without every part
        self.duplicates = 0  #: parts of a measurement already gathered whole, dropped

    @property
    def held(self) -> int:
        """Measurements held, some of their parts come, the rest awaited."""
        return len(self._open)

    def _total(self, header: dict, end: int) -> int:
        return int(header.get("n_tdc_total") or self.n_tdc or end)

    def _key(self, header: dict, batch: pa.RecordBatch) -> tuple[str, tuple[int, int], int]:
        from schemas.errors import Rejected

        rng = header.get("tdc_range") or [0, batch.num_rows]
        a, b = int(rng[0]), int(rng[1])
        total = self._total(header, b)
        if not 0 <= a < b <= total or batch.num_rows != b - a:
            raise Rejected("bad_payload", f"measurement {header.get('measurement')}: "
                           f"tdc_range {rng} of {total} TDCs with {batch.num_rows} rows")
        return str(header.get("measurement", header.get("run"))), (a, b), total

    def add(self, header: dict, batch: pa.RecordBatch) -> list[Frame]:
        """Take one part; the frames it completes or pushes out (oldest first)."""
        from schemas.errors import Rejected

        name, rng, total = self._key(header, batch)
        same = (bool(header.get("partial")), header.get("words"))
        if self._done.get(name, {}).get(rng) == same:
            self.duplicates += 1
            return []
        parts = self._open.setdefault(name, {})
        for a, b in parts:
            if (a, b) != rng and a < rng[1] and rng[0] < b:
                raise Rejected("bad_payload", f"measurement {name}: tdc_range {list(rng)} "
                               f"overlaps another part's {[a, b]}")
        parts[rng] = (header, batch)  # a part sent again replaces the one held
        out = []
        if sum(b - a for a, b in parts) == total:
            out.append(self._give(name, total))
        while len(self._open) > self.hold:
            oldest = min(self._open, key=lambda n: self._index(n))
            out.append(self._give(oldest, None))
        return out

    def flush(self) -> list[Frame]:
        """Every held measurement, oldest first (the stream's end)."""
        return [self._give(n, None) for n in sorted(self._open, key=self._index)]

    def _index(self, name: str) -> tuple:
        head = next(iter(self._open[name].values()))[0]
        return (int(head.get("measurement_index", head.get("seq", 0))), name)

    def _give(self, name: str, total: int | None) -> Frame:
        from stages.histogram import HistogramState

        parts = sorted(self._open.pop(name).items())
        head0 = parts[0][1][0]
        n = self._total(head0, parts[-1][0][1]) if total is None else total
        have = np.zeros(n, bool)
        states = []
        for (a, b), (_, batch) in parts:
            st = HistogramState.from_table(pa.Table.from_batches([batch]))
            states.append(((a, b), st))
            have[a:b] = True
        missing = _runs(~have)
        hits = np.zeros((n, states[0][1].hits.shape[1]), np.uint64)
        cc = np.zeros((states[0][1].class_counts.shape[0], n), np.uint64)
        for (a, b), st in states:
            hits[a:b], cc[:, a:b] = st.hits, st.class_counts
        if missing:
            hits[~have] = np.rint(hits[have].mean(axis=0)).astype(np.uint64)
            cc[:, ~have] = np.rint(cc[:, have].mean(axis=1)).astype(np.uint64)[:, None]
            self.incomplete += 1
        else:
            self._done[name] = {r: (bool(h.get("partial")), h.get("words"))
                                for r, (h, _) in parts}
            while len(self._done) > self.remember:
                self._done.pop(next(iter(self._done)))
        cycles = [h.get("cycles") for _, (h, _) in parts if h.get("cycles")]
        header = {k: v for k, v in head0.items() if k not in ("words", "class_counts")}
        header.update(tdc_range=[0, n], partial=any(h.get("partial") for _, (h, _) in parts),
                      **({"cycles": [min(c[0] for c in cycles), max(c[1] for c in cycles)]}
                         if cycles else {}))
        state = HistogramState(hits, cc, sum(st.words for _, st in states))
        return Frame(header, state, [(h, r) for r, (h, _) in parts], missing)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """The [first, end) runs of True in ``mask``."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist(),
                    strict=True))
