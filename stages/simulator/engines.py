"""Two engines that draw the first START of every TDC in every cycle, and the digitiser
that turns STARTs into first-stage codes.

Both engines return, for a chunk of ``n_cycles`` cycles (row-major cycle x TDC, the words'
order), the flat indices of TDC-cycles that saw a START, their kind (photon or artifact)
and, for photons, the arrival time ``t`` after the window opened (``t < 0``: during the
reset period, so the TDC starts at the window's beginning).

``fast``
    Exact inversion of the cumulative intensity: one uniform per TDC-cycle decides whether
    anything starts the TDC (``u > exp(-L(T))``); for those that start, ``E = -log u`` is
    the cumulative intensity at the first START. The artifact is a point mass of the
    intensity at its code's time, so the same E decides between photon and artifact. The
    continuous part is inverted on a per-TDC table and refined by bracketed Newton steps on
    the analytic L (exact to rounding). Static scenes only.
``reference``
    Photon by photon, following the thesis's random simulation (section 2.2.1, steps 1-3):
    every detected signal photon (laser pulse width and jitter, then SPAD jitter), every
    detected background and dark-count photon of the sensitive period, every artifact
    event; the earliest START wins. Slow, and supports motion (a TOF that drifts from
    cycle to cycle).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from stages.models.tcspc import SQRT2PI
from stages.simulator.chip import Chip

KIND_PHOTON, KIND_ARTIFACT = 0, 1
#: Time tolerance of the inversion (0.1 fs) and its iteration cap.
T_TOL = 1e-16
MAX_ITER = 60
#: A Newton step shorter than this (10 fs) ends the inversion after it is taken: Newton
#: converges quadratically, so the root lies within ~step^2 * |L''| / (2 L') < 1e-18 s of
#: the new point (the pulse's curvature scale is sigma > 10 ps); a further step only to
#: confirm it would cost one more erfc and exp. Bisection steps do not count.
NEWTON_DONE = 1e-14
#: Beyond this many sigma the pulse's CDF is 0 or 1 and its density 0 (to < 1e-32).
Z_FAR = 12.0
ENGINES = ("fast", "reference")


@dataclass(frozen=True)
class Optics:
    """What reaches each TDC, per cycle (arrays of length n_tdc)."""

    m_signal: np.ndarray        #: detected signal photons per cycle
    tof_s: np.ndarray           #: pulse centre after the window opened (0 where no signal)
    sigma_s: float              #: laser pulse + laser jitter + SPAD jitter (no TDC jitter)
    bg_hz: np.ndarray           #: detected background rate (ambient + dark counts)
    window_s: float
    reset_s: float
    tof_drift_s_per_cycle: np.ndarray | None = None  #: motion (reference engine only)
    #: the surfaces behind the first (n_tdc, K - 1): signal per cycle and arrival time, a
    #: partially transparent target's (reference engine only)
    extra_m: np.ndarray | None = None
    extra_tof_s: np.ndarray | None = None

    @property
    def n_tdc(self) -> int:
        return int(self.m_signal.size)

    @property
    def layered(self) -> bool:
        """More than one surface in some pixel."""
        return self.extra_m is not None and bool(np.any(self.extra_m > 0))

    @property
    def moving(self) -> bool:
        return self.tof_drift_s_per_cycle is not None and bool(
            np.any(self.tof_drift_s_per_cycle != 0))


@dataclass(frozen=True)
class Events:
    """Where a chunk's STARTs are: the TDC-cycles that saw one (flat indices) and the
    cumulative intensity at each (-log of its uniform). The rest of the chunk's random
    numbers follow in the generator's stream, in this order: a standard normal (the TDC's
    jitter) for each photon START, then a uniform (the D2nd) for each artifact START, both
    in the order of the STARTs here (``draw_tails``)."""

    index: np.ndarray
    e: np.ndarray  #: -log(u): the cumulative intensity at the START
    tdc: np.ndarray | None = None  #: index % n_tdc, when known
    flat: np.ndarray | None = None  #: TDC-major place (tdc * n_cycles + cycle), when known


def draw_tails(rng: np.random.Generator, artifact: np.ndarray):
    """The TDC jitter's standard normal of each photon START (0 for artifacts) and the
    uniform of each artifact START (0 for photons), drawn in the order of :class:`Events`
    (the compiled kernel draws the same numbers one at a time)."""
    z = np.zeros(artifact.size)
    r = np.zeros(artifact.size)
    z[~artifact] = rng.standard_normal(artifact.size - int(artifact.sum()))
    r[artifact] = rng.random(int(artifact.sum()))
    return z, r


@dataclass(frozen=True)
class Starts:
    """The TDC-cycles of a chunk that saw a START."""

    index: np.ndarray   #: flat index cycle * n_tdc + tdc
    kind: np.ndarray    #: KIND_PHOTON or KIND_ARTIFACT
    t_s: np.ndarray     #: photon arrival after the window opened (NaN for artifacts)
    code: np.ndarray    #: artifact code (-1 for photons)


def _artifact_times(chip: Chip, optics: Optics, boundaries: np.ndarray):
    """Artifact START times (n_tdc, n_art), ascending, and their probabilities."""
    c = chip.artifact_codes
    tau = 0.5 * (boundaries[:, c] + boundaries[:, c + 1])
    t = optics.window_s - tau
    order = np.argsort(t, axis=1)
    p = np.broadcast_to(chip.artifact_prob[:, None] / max(c.size, 1), t.shape)
    return np.take_along_axis(t, order, 1), np.take_along_axis(p, order, 1), c[order]


class FastEngine:
    """Exact inversion of the cumulative intensity (see module docstring)."""

    name = "fast"

    def __init__(self, chip: Chip, optics: Optics, boundaries: np.ndarray,
                 grid_points: int = 4097, inverse_points: int = 2049):
        if optics.moving:
            raise ValueError("the fast engine draws static scenes only; a moving target "
                             "needs engine='reference'")
        if optics.layered:
            raise ValueError("the fast engine draws one surface a pixel; a scene with a "
                             "partially transparent target (transmittance > 0 in front of "
                             "another) needs engine='reference'")
        self.o = optics
        s, T = -optics.reset_s, optics.window_s
        self.start, self.end = s, T
        grid = np.linspace(s, T, grid_points)
        m, tof, sg, bg = (optics.m_signal[:, None], optics.tof_s[:, None], optics.sigma_s,
                          optics.bg_hz[:, None])
        # the continuous cumulative intensity L_c(t) from the start of sensitivity
        table = m * (ndtr((grid[None, :] - tof) / sg) - ndtr((s - tof) / sg)) + bg * (
            grid[None, :] - s)                                          # (n_tdc, G)
        self.l_end = table[:, -1]
        self.phi0 = ndtr((s - optics.tof_s) / sg)
        self.inv_sigma = 1.0 / sg
        self.k_pdf = 1.0 / (SQRT2PI * sg)
        # its inverse on a uniform grid of E per TDC: t(E_j), E_j = j * l_end / (P - 1)
        n_tdc = optics.n_tdc
        self.de = np.where(self.l_end > 0, self.l_end / (inverse_points - 1), 1.0)
        self.inv_de = 1.0 / self.de
        self.inv = np.empty((n_tdc, inverse_points))
        for i in range(n_tdc):  # once per simulation
            e = np.arange(inverse_points) * self.de[i]
            if self.l_end[i] == 0:
                self.inv[i] = np.linspace(s, T, inverse_points)
                continue
            k = np.clip(np.searchsorted(table[i], e, side="right") - 1, 0, grid.size - 2)
            dl = np.maximum(table[i][k + 1] - table[i][k], 1e-300)
            self.inv[i] = self._newton(i, e, grid[k], grid[k + 1], table[i][k], 1.0 / dl)
        self.inv[:, 0], self.inv[:, -1] = s, T
        # artifacts: point masses of the intensity at fixed times
        t_a, p_a, c_a = _artifact_times(chip, optics, boundaries)
        inside = (t_a >= s) & (t_a < T)
        self.c_a = c_a
        self.m_a = np.where(inside, -np.log1p(-p_a), 0.0)
        lc_at = np.array([np.interp(t_a[i], grid, table[i]) for i in range(n_tdc)])
        lc_at = lc_at.reshape(t_a.shape)
        below = np.concatenate([np.zeros_like(self.m_a[:, :1]),
                                np.cumsum(self.m_a, 1)[:, :-1]], 1)
        self.j_lo = lc_at + below                  # L just before artifact j
        self.j_hi = self.j_lo + self.m_a           # ... and just after
        self.p_none = np.exp(-(self.l_end + self.m_a.sum(1)))

    def _newton(self, tdc, e, lo, hi, l_lo, inv_dl, iterations=MAX_ITER):
        """Solve L_c(t) = e inside [lo, hi] (f(lo) <= 0 <= f(hi)), vectorised.

        Safeguarded Newton: the bracket shrinks with every step, a step that would leave it
        bisects instead, and each element stops when its step is below ``T_TOL`` (0.1 fs).
        One plain Newton step is not enough where L turns from flat (background only) to
        steep (the pulse's onset): it overshoots to the cell's edge. Divisions are
        multiplications by reciprocals (the compiled kernel does the same arithmetic, so
        both write the same bytes).
        """
        o = self.o
        tdc = np.broadcast_to(tdc, np.shape(e))
        t = lo + (e - l_lo) * inv_dl * (hi - lo)
        t, lo, hi, e = (np.array(x, np.float64) for x in (t, lo, hi, e))
        phi0 = self.phi0
        inv_sg, k_pdf = self.inv_sigma, self.k_pdf
        # a cell wholly beyond Z_FAR on one side (or with no signal) is linear: one step
        # lands on the root
        zl, zh = (lo - o.tof_s[tdc]) * inv_sg, (hi - o.tof_s[tdc]) * inv_sg
        linear = (((zl > Z_FAR) & (zh > Z_FAR)) | ((zl < -Z_FAR) & (zh < -Z_FAR))
                  | (o.m_signal[tdc] == 0))
        # in a linear cell the interpolation between the exact table points is the root
        active = np.flatnonzero(~linear)
        for _ in range(iterations):
            if active.size == 0:
                break
            ta, ti = t[active], tdc[active]
            z = (ta - o.tof_s[ti]) * inv_sg
            # beyond Z_FAR sigma Phi is 0 or 1 and phi is 0 to < 1e-32: no special functions
            near = np.abs(z) <= Z_FAR
            cdf = (z > 0).astype(np.float64)
            pdf = np.zeros_like(z)
            cdf[near] = ndtr(z[near])
            pdf[near] = np.exp(-0.5 * (z[near] * z[near])) * k_pdf
            m = o.m_signal[ti]
            f = m * (cdf - phi0[ti]) + o.bg_hz[ti] * (ta - self.start) - e[active]
            rate = m * pdf + o.bg_hz[ti]
            lo[active] = np.where(f <= 0, ta, lo[active])
            hi[active] = np.where(f >= 0, ta, hi[active])
            with np.errstate(divide="ignore", invalid="ignore"):
                step = ta - f / rate
            la, ha = lo[active], hi[active]
            newton = (step > la) & (step < ha)
            new = np.where(newton, step, 0.5 * (la + ha))
            moved = np.abs(new - ta)
            done = ((moved < T_TOL) | (newton & (moved < NEWTON_DONE)) | (f == 0)
                    | (ha - la < T_TOL))
            t[active] = np.where(f == 0, ta, new)
            active = active[~done]
        return t

    def events(self, rng: np.random.Generator, n_cycles: int) -> Events:
        """Every random number a chunk needs, drawn in one fixed order.

        The uniforms are drawn TDC-major, so the STARTs come out grouped by TDC: the
        per-TDC tables stay in cache while they are used.
        """
        n_tdc = self.o.n_tdc
        u = rng.random((n_tdc, n_cycles))
        flat = np.flatnonzero(u > self.p_none[:, None])  # something starts the TDC
        tdc = flat // n_cycles
        index = (flat - tdc * n_cycles) * n_tdc + tdc     # the word's place: cycle-major
        e = -np.log(u.ravel()[flat])                      # cumulative intensity at START
        return Events(index, e, tdc, flat)

    def draw(self, rng: np.random.Generator, n_cycles: int) -> Starts:
        return self.starts(self.events(rng, n_cycles))

    def starts(self, ev: Events) -> Starts:
        """The numpy inversion: where each START of ``ev`` happened."""
        n_tdc = self.o.n_tdc
        index = ev.index
        tdc = ev.tdc if ev.tdc is not None else index % n_tdc
        e = ev.e
        code = np.full(index.size, -1, np.int64)
        below = np.zeros(index.size)
        n_art = self.m_a.shape[1]
        j_lo, j_hi = self.j_lo.ravel(), self.j_hi.ravel()
        for j in range(n_art):                     # the few artifact codes
            flat = tdc * n_art + j
            lo, hi = j_lo[flat], j_hi[flat]
            hit = (e >= lo) & (e < hi)
            if hit.any():
                code[hit] = self.c_a.ravel()[flat[hit]]
            above = e >= hi
            below[above] += self.m_a.ravel()[flat[above]]
        art = code >= 0
        kind = art.astype(np.int8)                 # KIND_ARTIFACT == 1
        t = np.full(index.size, np.nan)
        ph = ~art
        tp, ec = tdc[ph], np.minimum(e[ph] - below[ph], self.l_end[tdc[ph]])
        x = ec * self.inv_de[tp]
        n_inv = self.inv.shape[1]
        j = np.minimum(x.astype(np.int64), n_inv - 2)
        flat = tp * n_inv + j
        inv = self.inv.ravel()
        lo, hi = inv[flat], inv[flat + 1]
        t[ph] = self._newton(tp, ec, lo, hi, j * self.de[tp], self.inv_de[tp])
        return Starts(index, kind, t, code)


class ReferenceEngine:
    """Photon by photon (see module docstring)."""

    name = "reference"

    def __init__(self, chip: Chip, optics: Optics, boundaries: np.ndarray,
                 spad_sigma_s: float | None = None):
        self.o = optics
        self.start, self.end = -optics.reset_s, optics.window_s
        t_a, p_a, c_a = _artifact_times(chip, optics, boundaries)
        self.t_a, self.p_a, self.c_a = t_a, p_a, c_a
        # the optical sigma splits into the pulse (+ laser jitter) and the SPAD's jitter
        self.spad_sigma = optics.sigma_s if spad_sigma_s is None else spad_sigma_s
        self.pulse_sigma = np.sqrt(max(optics.sigma_s ** 2 - self.spad_sigma ** 2, 0.0))
        self.cycle0 = 0

    def draw(self, rng: np.random.Generator, n_cycles: int, first_cycle: int = 0) -> Starts:
        o = self.o
        n_tdc = o.n_tdc
        span = self.end - self.start
        cells = n_cycles * n_tdc
        first = np.full(cells, np.inf)
        # signal photons: Poisson(M) detections per TDC-cycle, pulse time + SPAD jitter
        k = rng.poisson(np.tile(o.m_signal, n_cycles))
        cell = np.repeat(np.arange(cells), k)
        tof = o.tof_s[cell % n_tdc]
        if o.moving:
            cyc = first_cycle + cell // n_tdc
            tof = tof + o.tof_drift_s_per_cycle[cell % n_tdc] * cyc
        ts = rng.normal(tof, self.pulse_sigma if self.pulse_sigma > 0 else 1e-300)
        ts = ts + rng.normal(0.0, self.spad_sigma, ts.size)
        keep = ts >= self.start
        np.minimum.at(first, cell[keep], ts[keep])
        for j in range(o.extra_m.shape[1] if o.layered else 0):  # surfaces behind the first
            k = rng.poisson(np.tile(o.extra_m[:, j], n_cycles))
            cell = np.repeat(np.arange(cells), k)
            ts = rng.normal(o.extra_tof_s[cell % n_tdc, j],
                            self.pulse_sigma if self.pulse_sigma > 0 else 1e-300)
            ts = ts + rng.normal(0.0, self.spad_sigma, ts.size)
            keep = ts >= self.start
            np.minimum.at(first, cell[keep], ts[keep])
        # background and dark-count detections over the sensitive period
        kb = rng.poisson(np.tile(o.bg_hz * span, n_cycles))
        cell_b = np.repeat(np.arange(cells), kb)
        tb = self.start + rng.random(cell_b.size) * span
        np.minimum.at(first, cell_b, tb)
        # artifact events at their fixed times
        art_t = np.full(cells, np.inf)
        art_c = np.full(cells, -1, np.int64)
        for j in range(self.t_a.shape[1]):
            ev = rng.random(cells) < np.tile(self.p_a[:, j], n_cycles)
            tj = np.tile(self.t_a[:, j], n_cycles)
            take = ev & (tj < art_t) & (tj >= self.start)
            art_t = np.where(take, tj, art_t)
            art_c = np.where(take, np.tile(self.c_a[:, j], n_cycles), art_c)
        photon = (first < self.end) & (first <= art_t)
        artifact = (art_t < self.end) & (art_t < first)
        index = np.flatnonzero(photon | artifact)
        kind = np.where(artifact[index], KIND_ARTIFACT, KIND_PHOTON).astype(np.int8)
        t = np.where(kind == KIND_PHOTON, first[index], np.nan)
        code = np.where(kind == KIND_ARTIFACT, art_c[index], -1)
        return Starts(index, kind, t, code)


class CodeTable:
    """Code lookup of every TDC: a uniform grid of tau (1/4 LSB) gives the code at each
    cell's left edge; a cell is narrower than any code (DNL > -0.55 LSB, so codes are wider
    than 0.45 LSB), so it holds at most one boundary and one comparison settles the code.
    int16 at 4 points per LSB keeps the table at 512 KiB for 128 TDCs (cache-resident).
    A dead code (zero width: the chip zoo's) is never output: crossing a boundary goes to
    the next live code (``next_live``)."""

    def __init__(self, boundaries: np.ndarray, per_lsb: int = 4):
        self.b = boundaries
        n_tdc, n = boundaries.shape
        self.period = boundaries[:, -1]
        self.step = self.period / ((n - 1) * per_lsb)
        grid = np.arange((n - 1) * per_lsb) * self.step[:, None]
        self.code = np.empty(grid.shape, np.int16)
        for i in range(n_tdc):  # once per simulation
            self.code[i] = np.searchsorted(boundaries[i], grid[i], side="right") - 1
        widths = np.diff(boundaries, axis=1)
        live = widths > 0
        if np.any(live & (widths <= self.step[:, None])):
            raise ValueError("a code is narrower than the lookup grid: raise per_lsb")
        self.inv_step = 1.0 / self.step
        self.inv_width = np.divide(1.0, widths, out=np.zeros_like(widths), where=live)
        # the code after k that has a width (k + 1 but past a dead code), per TDC
        self.next_live = np.tile(np.arange(1, n + 1, dtype=np.int64), (n_tdc, 1))
        for i, k in zip(*np.nonzero(~live), strict=True):  # the few dead codes
            self.next_live[i, :k][self.next_live[i, :k] == k] = self.next_live[i, k]

    def lookup(self, tdc: np.ndarray, tau: np.ndarray):
        x = np.mod(tau, self.period[tdc])          # the 9-bit counter wraps
        n_g, n_b = self.code.shape[1], self.b.shape[1]
        g = np.minimum((x * self.inv_step[tdc]).astype(np.int64), n_g - 1)
        k = self.code.ravel()[tdc * n_g + g].astype(np.int64)
        b = self.b.ravel()
        cross = x >= b[tdc * n_b + np.minimum(k + 1, n_b - 1)]
        k = np.minimum(np.where(cross, self.next_live.ravel()[tdc * n_b + k], k), n_b - 2)
        frac = (x - b[tdc * n_b + k]) * self.inv_width.ravel()[tdc * (n_b - 1) + k]
        return k, np.clip(frac, 0.0, np.nextafter(1.0, 0.0))


def digitize(codes: CodeTable, jitter_s: np.ndarray, window_s: float, starts: Starts,
             n_tdc: int, z: np.ndarray, reset_offset_s: float = 0.0,
             reset_jitter_s: np.ndarray | None = None):
    """Codes (D1st) and fractional positions of photon STARTs; artifact codes pass through.

    ``tau = window - t`` (reversed timing; a START in the reset period is the window's
    beginning, tau = window, or ``window + reset_offset_s`` on a chip of the zoo), plus the
    TDC's Gaussian jitter (``reset_jitter_s`` for the reset period's STARTs, where given),
    then the code whose boundaries hold it; codes wrap at 512 (9 bits).
    """
    tdc = starts.index % n_tdc
    photon = starts.kind == KIND_PHOTON
    t = np.nan_to_num(starts.t_s, nan=0.0)
    tau = window_s - np.clip(t, 0.0, window_s)     # t < 0: the reset period, tau = window
    reset = t < 0
    if reset_offset_s:
        tau = np.where(reset, tau + reset_offset_s, tau)
    jitter = jitter_s[tdc] if reset_jitter_s is None else np.where(
        reset, reset_jitter_s[tdc], jitter_s[tdc])
    tau = np.maximum(tau + z * jitter, 0.0)
    code, frac = codes.lookup(tdc, tau)
    return tdc, np.where(photon, code, starts.code), frac


try:  # the fast engine's per-START work compiles where numba is installed
    import numba
except ImportError:  # pragma: no cover
    numba = None

if numba is not None:
    import math

    @numba.njit(cache=True, nogil=True)
    def _fast_kernel(index, tdc_ev, e_ev, rng, n_tdc, j_lo, j_hi, m_a, c_a, l_end, de,
                     inv_de, inv, m_sig, tof, bg, inv_sg, k_pdf, start, phi0, window, jitter,
                     period, inv_step, code_tab, bnd, inv_w, n_th, n_min, n_max, johnson,
                     words, is_artifact, next_live, reset_off, reset_jit, d2_edges,
                     d2_time):
        n_art = j_lo.shape[1]
        n_inv = inv.shape[1]
        n_g = code_tab.shape[1]
        n_b = bnd.shape[1]
        for q in range(index.size):  # STARTs come grouped by TDC (Events)
            i = index[q]  # TDC-major place in words (see fast_chunk_numba)
            t = tdc_ev[q]
            e = e_ev[q]
            below = 0.0
            acode = -1
            for j in range(n_art):  # without branches: e falls anywhere among them
                lo_j = j_lo[t, j]
                hi_j = j_hi[t, j]
                below += m_a[t, j] * (e >= hi_j)
                acode += (c_a[t, j] + 1) * ((e >= lo_j) & (e < hi_j))  # disjoint: one at most
            if acode >= 0:  # its D2nd after the loop (draw_tails' order)
                is_artifact[q] = True
                words[i] = ((acode >> 3) << 16) | (johnson[acode & 7] << 12) | (1 << 9) | (
                    t << 1)
                continue
            else:
                ec = min(e - below, l_end[t])
                jj = min(int(ec * inv_de[t]), n_inv - 2)
                lo_t = inv[t, jj]
                hi_t = inv[t, jj + 1]
                l_lo = jj * de[t]
                tt = lo_t + (ec - l_lo) * inv_de[t] * (hi_t - lo_t)
                zl = (lo_t - tof[t]) * inv_sg
                zh = (hi_t - tof[t]) * inv_sg
                linear = ((zl > Z_FAR and zh > Z_FAR) or (zl < -Z_FAR and zh < -Z_FAR)
                          or m_sig[t] == 0)
                for _ in range(0 if linear else MAX_ITER):  # as FastEngine._newton
                    zz = (tt - tof[t]) * inv_sg
                    if zz > Z_FAR:
                        cdf, pdf = 1.0, 0.0
                    elif zz < -Z_FAR:
                        cdf, pdf = 0.0, 0.0
                    else:
                        cdf = 0.5 * math.erfc(-zz / math.sqrt(2.0))
                        pdf = math.exp(-0.5 * (zz * zz)) * k_pdf
                    f = m_sig[t] * (cdf - phi0[t]) + bg[t] * (tt - start) - ec
                    if f == 0:
                        break
                    rate = m_sig[t] * pdf + bg[t]
                    if f < 0:
                        lo_t = tt
                    else:
                        hi_t = tt
                    nt = tt - f / rate if rate > 0 else lo_t
                    newton = lo_t < nt < hi_t
                    new = nt if newton else 0.5 * (lo_t + hi_t)
                    moved = abs(new - tt)
                    done = (moved < T_TOL or (newton and moved < NEWTON_DONE)
                            or hi_t - lo_t < T_TOL)
                    tt = new
                    if done:
                        break
                if tt < 0.0:  # the reset period: the window's beginning (+ the zoo's offset)
                    tau = max(window + reset_off + rng.standard_normal() * reset_jit[t], 0.0)
                else:
                    tau = window - min(tt, window)
                    tau = max(tau + rng.standard_normal() * jitter[t], 0.0)
                x = tau
                while x >= period[t]:  # the 9-bit counter wraps
                    x -= period[t]
                g = min(int(x * inv_step[t]), n_g - 1)
                k = np.int64(code_tab[t, g])
                if x >= bnd[t, min(k + 1, n_b - 1)]:
                    k = next_live[t, k]
                k = min(k, n_b - 2)
                frac = (x - bnd[t, k]) * inv_w[t, k]
                frac = min(max(frac, 0.0), 1.0 - 1e-16)
                w = n_max[t] - n_min[t] + 1
                # codes are >= 0: & 7 and >> 3 are % 8 and // 8 without Python's sign rules
                if d2_time:  # the zoo's second stage in time (as chip.second_stage)
                    k8 = k - (k & 7)
                    f = (bnd[t, k] + frac * (bnd[t, k + 1] - bnd[t, k]) - bnd[t, k8]) / (
                        bnd[t, k8 + 8] - bnd[t, k8])
                    f = min(max(f, 0.0), 1.0 - 1e-16)
                else:
                    f = ((k & 7) + frac) / 8.0
                if d2_edges.shape[1] == 0:
                    if d2_time:
                        mod = min(int(f * w), w - 1)
                    else:
                        mod = min(int(((k & 7) + frac) / 8.0 * w), w - 1)
                else:  # the zoo's second-stage DNL: searchsorted(edges, f, "right") - 1
                    a, b = 0, d2_edges.shape[1]
                    while a < b:
                        c = (a + b) // 2
                        if d2_edges[t, c] <= f:
                            a = c + 1
                        else:
                            b = c
                    mod = min(max(a - 1, 0), w - 1)
                d2 = n_th[t] + mod
                d2 -= w * (d2 > n_max[t])
                is_artifact[q] = False
            words[i] = ((d2 >> 3) << 26) | (johnson[d2 & 7] << 22) | ((k >> 3) << 16) | (
                johnson[k & 7] << 12) | (1 << 9) | (t << 1)
        for q in range(index.size):  # the artifacts' D2nd, above Nmax
            if is_artifact[q]:
                t = tdc_ev[q]
                lo2 = n_max[t] + 1
                d2 = lo2 + int(rng.random() * (256 - lo2))
                words[index[q]] |= ((d2 >> 3) << 26) | (johnson[d2 & 7] << 22)


def fast_chunk_numba(engine: FastEngine, chip: Chip, codes: CodeTable, jitter_s: np.ndarray,
                     ev: Events, rng: np.random.Generator, words_t: np.ndarray,
                     reset_jitter_s: np.ndarray | None = None) -> np.ndarray:
    """Fill the TDC-major words ``words_t`` (n_tdc, n_cycles) at the STARTs of ``ev``;
    returns which STARTs are artifacts. TDC-major writes are sequential per TDC; the caller
    transposes once (cycle-major scattered writes missed the cache at almost every START).
    """
    from stages.codec import PHASE_ENCODE

    o = engine.o
    art = np.empty(ev.index.size, np.bool_)
    words = words_t.reshape(-1)
    _fast_kernel(ev.flat, ev.tdc, ev.e, rng, o.n_tdc, engine.j_lo, engine.j_hi,
                 engine.m_a, engine.c_a, engine.l_end, engine.de, engine.inv_de, engine.inv,
                 o.m_signal, o.tof_s, o.bg_hz, engine.inv_sigma, engine.k_pdf, engine.start,
                 engine.phi0, o.window_s, jitter_s, codes.period, codes.inv_step, codes.code,
                 codes.b, codes.inv_width, chip.n_th, chip.n_min, chip.n_max,
                 PHASE_ENCODE.astype(np.int64), words, art, codes.next_live,
                 chip.reset_offset_ps * 1e-12,
                 jitter_s if reset_jitter_s is None else reset_jitter_s,
                 np.zeros((o.n_tdc, 0)) if chip.d2nd_edges is None else chip.d2nd_edges,
                 bool(chip.d2nd_in_time))
    return art
