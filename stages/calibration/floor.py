"""The counting floor of the delay (issue 33): the Cramér-Rao bound on the time of a code at
a light, from the counts a campaign of density tests expects, whatever the estimator.

The delay reads the return's code ``c`` on the time axis at the zero capture's light:
``tau_c = T B(c) / B(x_T0)``, ``B`` the code boundaries in any unit and ``x_T0`` where tau =
T falls at that light. Its error is ``tau_c`` times the error of ``g = log B(c) - log
B(x_T0)``: the share of the window's time below code ``c``, which only the code widths
set, never a test's own LSB or light.

A density test's cycle is a sequence of chances in arrival order (the reset period, then
the codes from the top down): code k fires with probability ``1 - exp(-u_k)`` among the
cycles still at risk ``R_k``, ``u_k = lambda_i w_k`` (the test's light per unit of width
times the code's width). The likelihood is a product of independent binomials, one a code,
so the Fisher information on ``u_k`` is exactly ``R_k (1 - p_k) / p_k``, ``p_k = h_k / R_k``
(the inverse of Coates' variance, :func:`stages.calibration.density._coates_var`), the
codes independent. With every test's ``lambda_i`` free (the LSB and the light change from
test to test; the widths do not), the parameters are ``log w_k`` and ``log lambda_i``; the
information is ``J = sum_i sum_k I_ik u_ik^2 a_ik a_ik^T``, ``a_ik`` the indicator of
``log w_k`` and ``log lambda_i``; one direction (every ``w`` up, every ``lambda`` down by
as much) is not measured and ``g`` does not depend on it, so ``lambda_0`` is held. Then
``var g >= grad(g)^T J^-1 grad(g)``.

Which codes a test measures: those whose upper boundary lies ``margin`` codes or more
below its own x_T (the chain's :data:`stages.calibration.density.OWN_CLEAR_LSB`, 2.5; the
codes above hold the reset peak's tail and the light's blurred end). A code of the zero's
window no test measures has no bound (inf).

Rule of thumb (one test, no pile-up, every code measured): ``g``'s error is binomial,
``sqrt(F (1 - F) / N)``, ``F = B(c) / B(x_T0)`` and N the test's hits in its window, and
the delay's ``T`` times that (``T``, not ``tau_c``: the share is of the whole window). Four
tests add their information only over the codes each measures.
"""

from __future__ import annotations

import numpy as np

from stages.calibration.reset_peak import at_risk_by_code


def tau_floor_s(tests, widths, code: float, x_t0, window_s: float,
                margin: float = 2.5, unmeasured_sd: float | None = None,
                known_from=None) -> np.ndarray:
    """(n_tdc,) the Cramér-Rao bound (standard deviation, s) on ``tau`` of boundary ``code``
    at the light where tau = T falls at code ``x_t0`` (n_tdc,).

    ``tests``: ``(hits, cycles, x_t)`` per density test, ``hits`` (n_tdc, 512) the counts
    it expects (noise-free: :func:`stages.simulator.expected.expected_density_hits`),
    ``cycles`` (n_tdc,), ``x_t`` (n_tdc,) where its window ends on the code axis; a fourth
    item, (n_tdc, 512) bool, keeps only those codes (a capture with a return: its uniform
    light measures the codes clear of it).
    ``widths`` (n_tdc, 512): the chip's code widths in any unit (only their ratios count).
    ``unmeasured_sd``: the relative error of the width of a code of the zero's window that
    no test measures (the random DNL about the phase pattern that continues the table, a
    prior, not counting; 0: taken as known); None: such a TDC has no bound (inf).
    ``known_from`` (n_tdc,): the widths of the codes from there up taken as known (what
    the rest of the window costs; their counts still measure each test's light).
    """
    widths = np.asarray(widths, np.float64)
    n_tdc = widths.shape[0]
    x_t0 = np.broadcast_to(np.asarray(x_t0, np.float64), (n_tdc,))
    known_from = (np.full(n_tdc, np.inf) if known_from is None
                  else np.broadcast_to(np.asarray(known_from, np.float64), (n_tdc,)))
    info = []
    for hits, cycles, x_t, *usable in tests:
        h = np.asarray(hits, np.float64)
        r = at_risk_by_code(h, cycles)
        k = np.arange(h.shape[1])[None, :]
        measured = (k + 1 <= np.asarray(x_t, np.float64)[:, None] - margin) & (h > 0) \
            & (r > h)
        if usable:
            measured &= np.asarray(usable[0], bool)
        with np.errstate(divide="ignore", invalid="ignore"):
            u = -np.log1p(-h / r)
            fisher = r * (r - h) / h          # 1 / var(u), per code
            info.append(np.where(measured, fisher * u * u, 0.0))  # on log w_k, log lam_i
    out = np.full(n_tdc, np.nan)
    n_t = len(info)
    for t in range(n_tdc):
        top = int(np.floor(x_t0[t]))
        m = top + 1                                   # codes 0..top
        frac = x_t0[t] - top
        w = widths[t, :m]
        reach = np.ones(m)
        reach[top] = frac
        s_c = w[:int(code)].sum()
        s_t = (w * reach).sum()
        grad = np.concatenate([w * (np.arange(m) < code) / s_c - w * reach / s_t,
                               np.zeros(n_t)])
        a = np.array([i[t, :m] for i in info])     # (n_t, m)
        cover = a.sum(axis=0)
        jac = np.zeros((m + n_t, m + n_t))
        jac[np.arange(m), np.arange(m)] = cover
        jac[m + np.arange(n_t), m + np.arange(n_t)] = a.sum(axis=1)
        jac[:m, m:] = a.T
        jac[m:, :m] = a
        blind = (cover <= 0) & (w * reach > 0)     # in the window, no test measured it
        if blind.any() and unmeasured_sd is None:
            out[t] = np.inf
            continue
        known = np.arange(m) >= known_from[t]
        if blind.any() and unmeasured_sd == 0:
            known |= blind
        elif blind.any():
            jac[np.flatnonzero(blind), np.flatnonzero(blind)] += 1 / unmeasured_sd ** 2
        # lambda_0 held (the unmeasured direction); known widths and codes of zero width
        # and no count out of the system
        live = ~known & ((cover > 0) | blind)
        keep = np.r_[np.flatnonzero(live), m + np.arange(1, n_t)]
        g = grad[keep]
        var = float(g @ np.linalg.solve(jac[np.ix_(keep, keep)], g))
        out[t] = window_s * s_c / s_t * np.sqrt(max(var, 0.0))
    return out
