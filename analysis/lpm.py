"""The robust local polynomial method (LPM) for periodic excitations: the BLA of a record
that starts from rest or drifts, from all its periods.

After Pintelon, Schoukens, Vandersteen and Barbé, "Estimation of nonparametric noise
and FRF models for multivariable systems - Part I: Theory", MSSP 24 (2010) 573-595, and
Pintelon, Vandersteen, Schoukens and Rolain, "Improved (non-)parametric identification
of dynamic systems excited by periodic signals", MSSP 25 (2011) 2683-2704.

The DFT of the whole record of P periods (P N samples) holds the periodic response only
at the bins l = k P of the period's lines k; the bins in between hold noise and whatever
is not periodic: a transient (the response to the initial state) and a drift. Both are
smooth functions of the frequency, the periodic response at the lines is not. At each
line, a polynomial of degree R in the bin offset is fitted by least squares to the
2 n nearest bins that are not multiples of P (n on each side where the band allows);
its value at the line is the transient there, subtracted from the line. The fit's
residuals (q = 2 n - R - 1 degrees of freedom) give the noise variance of the bins and
the input-output covariance; the corrected line's variance is that times
(1 + ||w||^2), w the fit's weights at the line. A noise variance that is the same in
every period and the plain robust BLA are then computed from these (period-mean) line
moments as from the period-to-period ones (:func:`fftune.analysis.bla.robust_bla`
calls :func:`lpm_moments` when its checks find a transient or a drift).
"""
from dataclasses import dataclass

import numpy as np

from fftune.analysis.errors import InputError

__all__ = ["LPMInfo", "lpm_moments", "lpm_offsets"]


@dataclass
class LPMInfo:
    """What the LPM removed.

    Attributes
    ----------
    transient_re_output_db : float
        Power of the transient (and drift) estimated at the excited lines of the output,
        re the output's power there (dB; the part the plain average would have kept is
        about this divided by P^2).
    transient_re_noise_db : float
        Median over the excited lines of |T|^2 / var(T) (dB): its size re its own
        standard error.
    lines_significant : int
        Excited lines where |T|^2 > 4 var(T) (summed over realizations).
    lines_needed : int
        Count that noise alone reaches with probability 1e-3.
    significant : bool
        lines_significant >= lines_needed.
    order, neighbours, dof : int
        R, 2 n, q = 2 n - R - 1.
    """

    transient_re_output_db: float
    transient_re_noise_db: float
    lines_significant: int
    lines_needed: int
    significant: bool
    order: int
    neighbours: int
    dof: int


def lpm_offsets(line_bin, n_periods, n_side, n_full):
    """The 2 n_side bins nearest to ``line_bin`` (in the full-record DFT) that are not
    multiples of ``n_periods``, inside 1 .. n_full - 1 (n_side on each side when the
    edges allow, else more on the other side). Returns the offsets, sorted."""
    from itertools import islice
    p = n_periods
    below = list(islice((b for b in range(line_bin - 1, 0, -1) if b % p), 2 * n_side))
    above = list(islice((b for b in range(line_bin + 1, n_full) if b % p), 2 * n_side))
    lo = min(n_side, len(below))
    hi = min(2 * n_side - lo, len(above))
    lo = min(2 * n_side - hi, len(below))
    picked = below[:lo] + above[:hi]
    return np.array(sorted(b - line_bin for b in picked), dtype=np.int64)


def _fit_weights(offsets, order, scale):
    """LS fit of a degree-``order`` polynomial: the weights w of its value at 0 and an
    orthonormal basis Q of the polynomials at the offsets (the fit's projector is
    Q Q^T, so the residual's squared norm is |x|^2 - |Q^T x|^2)."""
    K = (offsets[:, None] / scale) ** np.arange(order + 1)[None, :]
    pinv = np.linalg.pinv(K)
    Q, _ = np.linalg.qr(K)
    return pinv[0], Q


def _dot_rows(v, B, rows=1024):
    """v @ B (v tall, B small, both float64) in blocks of ``rows`` rows: each block is
    under OpenBLAS's size for threading, so no thread is woken (and left spinning) for
    what one core does in well under a millisecond; the result is the same product."""
    out = np.empty((v.shape[0], B.shape[1]))
    for s in range(0, v.shape[0], rows):
        np.dot(v[s:s + rows], B, out=out[s:s + rows])
    return out


def lpm_moments(u, y, r=None, *, band, excited, settle_periods=0, order=2, n_side=6):
    """Line moments of the kept periods with the transient removed (robust LPM).

    Parameters
    ----------
    u, y : ndarray, shape (M, T + P, N)
        Input and output.
    r : ndarray, shape (M, T + P, N), optional
        Reference (taken as periodic: its period mean, no transient removed).
    band : ndarray of int
        Period lines k (consecutive) at which the moments are returned.
    excited : ndarray of int
        The excited lines (a subset of ``band``): the transient's size is judged there.
    settle_periods : int
        T, dropped.
    order : int
        Polynomial degree R.
    n_side : int
        Neighbours per side n (q = 2 n - R - 1 degrees of freedom).

    Returns
    -------
    (LineMoments, ndarray, LPMInfo)
        The moments (period means with the transient removed; ``ss_*`` and ``s_yu`` set
        so that ss / (P (P - 1)) is the variance of the corrected mean, the convention of
        :class:`fftune.analysis.bla.LineMoments`), per realization the mean and the
        P (P - 1)-scaled variance of G = Y / U at the excited lines (the estimate
        without a reference), and what was removed.
    """
    from fftune.analysis.bla import LineMoments, _false_alarm_count

    m_real, n_total, n = u.shape
    settle = int(settle_periods)
    p = n_total - settle
    if p < 2:
        raise InputError("local polynomial method: needs P >= 2 periods")
    if 2 * n_side <= order + 1:
        raise InputError(f"local polynomial method: 2 n = {2 * n_side} neighbours cannot fit a "
                         f"degree {order} polynomial with noise left over")
    band = np.asarray(band, dtype=np.int64)
    n_full = p * n // 2 + 1
    lines = band * p
    # the offset pattern of every line: the lines are multiples of P, so every line far
    # enough from DC and fs/2 has the same one (fitted once); the others on their own
    interior = lpm_offsets(int(p * (4 * n_side + 2)), p, n_side, 10 ** 12)
    inside = (lines + interior[0] >= 1) & (lines + interior[-1] < n_full)
    patterns = {tuple(interior): list(np.flatnonzero(inside))} if inside.any() else {}
    for i in np.flatnonzero(~inside):
        off = lpm_offsets(int(lines[i]), p, n_side, n_full)
        patterns.setdefault(tuple(off), []).append(i)
    q = 2 * n_side - order - 1
    L = band.size
    groups = []
    for off, idx in patterns.items():
        off = np.array(off)
        w, Q = _fit_weights(off, order, float(p))
        groups.append((np.array(idx), off, np.column_stack((w, Q))))

    # an input that repeats exactly (a generator's signal, open loop) has no transient:
    # its line sums are P times one period's, with no variance (one FFT saved)
    u_exact = all(bool((u[m, settle + 1:] == u[m, settle]).all()) for m in range(m_real))
    Yt, Ut = np.empty((m_real, L), complex), np.empty((m_real, L), complex)
    Yc, Uc = np.empty((m_real, L), complex), np.empty((m_real, L), complex)
    ss = {key: np.empty((m_real, L)) for key in ("yy", "uu")}
    s_yu = np.empty((m_real, L), complex)
    s_w = np.empty(L)
    keys = ("y",) if u_exact else ("y", "u")
    # one realization at a time, into buffers allocated once: its full-record spectra
    # and the neighbours of its lines stay in cache (fresh multi-megabyte temporaries
    # for all realizations at once cost page faults comparable to the arithmetic)
    spec = {key: np.empty(n_full, complex) for key in keys}
    fits = []
    for idx, off, B in groups:
        sel = lines[idx][:, None] + off[None, :]
        # B on the interleaved (re, im) view: one real product for both parts
        B2 = np.zeros((2 * off.size, 2 * B.shape[1]))
        B2[0::2, 0::2] = B
        B2[1::2, 1::2] = B
        fits.append((idx, sel, B2, {key: np.empty(sel.shape, complex) for key in keys}))
        s_w[idx] = float(np.sum(B[:, 0] ** 2))
    for m in range(m_real):
        for key in keys:
            x = np.asarray((y if key == "y" else u)[m, settle:], dtype=np.float64)
            np.fft.rfft(x.reshape(-1), out=spec[key])
        for idx, sel, B2, nbs in fits:
            parts = {}
            for key in keys:
                nb = np.take(spec[key], sel, out=nbs[key], mode="clip")       # (l, 2n)
                v = nb.view(np.float64)
                cr = _dot_rows(v, B2)
                cv = cr[:, 2:]                          # Q^T x (re, im): the fit's part
                ss[key + key][m, idx] = np.einsum("nk,nk->n", v, v) - np.einsum("nk,nk->n", cv, cv)
                c = cr.view(np.complex128)
                parts[key] = (nb, c)
                (Yt if key == "y" else Ut)[m, idx] = c[:, 0]
            if u_exact:                         # (an exactly periodic input: nothing to fit)
                ss["uu"][m, idx] = 0.0
                Ut[m, idx] = 0.0
                s_yu[m, idx] = 0.0
            else:
                (ny, cy), (nu, cu) = parts["y"], parts["u"]
                # sum of res_y conj(res_u), res = (I - Q Q^T) x: x_y . conj(x_u) minus the fit's
                s_yu[m, idx] = (np.einsum("lk,lk->l", ny, np.conj(nu))
                                - np.einsum("lj,lj->l", cy[:, 1:], np.conj(cu[:, 1:])))
        Yc[m] = spec["y"][lines] - Yt[m]
        if not u_exact:
            Uc[m] = spec["u"][lines] - Ut[m]
    if u_exact:
        Uc = p * np.fft.rfft(np.asarray(u[:, settle], dtype=np.float64), axis=-1)[:, band]
    factor = (1.0 + s_w) / q                     # var of a corrected line sum per |res|^2
    var_y = np.maximum(ss["yy"], 0.0) * factor
    var_u = np.maximum(ss["uu"], 0.0) * factor
    cov_yu = s_yu * factor
    # period means and their variances; ss = P (P - 1) var(mean) (LineMoments' convention)
    k = p * (p - 1) / p ** 2
    U_mean, Y_mean = Uc / p, Yc / p
    mom_r = ss_r = None
    if r is not None:
        R = np.fft.rfft(np.asarray(r[:, settle:], dtype=np.float64), axis=-1)[..., band]
        mom_r = R.mean(axis=1)
        ss_r = np.zeros(mom_r.shape)
    mom = LineMoments(bins=band, n_periods=p, U=U_mean, Y=Y_mean, ss_u=var_u * k,
                      ss_y=var_y * k, s_yu=cov_yu * k, R=mom_r, ss_r=ss_r)
    # the estimate without a reference: G per realization, its variance by propagation
    pos = np.searchsorted(band, excited)
    with np.errstate(divide="ignore", invalid="ignore"):
        G_m = Yc[:, pos] / Uc[:, pos]
        var_g = (var_y[:, pos] + np.abs(G_m) ** 2 * var_u[:, pos]
                 - 2 * np.real(np.conj(G_m) * cov_yu[:, pos])) / np.abs(Uc[:, pos]) ** 2
    G_per = (G_m, np.maximum(var_g, 0.0) * p * (p - 1))
    # how large the removed transient is, at the excited lines of the output
    t_pow = np.abs(Yt[:, pos]) ** 2
    t_var = var_y[:, pos] * s_w[pos] / (1.0 + s_w[pos])
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = t_pow / t_var
    out_pow = float(np.sum(np.abs(Yc[:, pos]) ** 2))
    over = int(np.sum(ratio > 4.0))
    n_lines = int(ratio.size)
    p_line = (1.0 + 4.0 / q) ** (-q)           # F(2, 2 q) tail at 4
    need = _false_alarm_count(n_lines, p_line)
    med = float(np.nanmedian(ratio)) if ratio.size else float("nan")
    info = LPMInfo(
        transient_re_output_db=float(10 * np.log10(max(float(np.sum(t_pow)), 1e-300)
                                                    / max(out_pow, 1e-300))),
        transient_re_noise_db=float(10 * np.log10(med)) if med > 0 else float("-inf"),
        lines_significant=over, lines_needed=need, significant=bool(over >= need),
        order=int(order), neighbours=int(2 * n_side), dof=int(q))
    return mom, G_per, info
