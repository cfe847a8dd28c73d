"""Robust Best Linear Approximation (BLA) from periodic multisine experiments.

Data layout: arrays shaped ``(M, T + P, N)`` -- M realizations (different random phases),
T settle periods (dropped from the estimate, used by the transient check) followed by P
steady-state periods, N samples per period. Frequencies are DFT bins k of one period:
f = k fs / N.

Formulas (docs/method.md section 2, after the paper "Frequency domain based feed
forward tuning for friction compensation" and Pintelon and Schoukens, "System
Identification", robust method), with G[m, p] = Y[m, p] / U[m, p] at the excited lines:

* G_m = mean_p G[m, p];  s2n_m = sum_p |G[m, p] - G_m|^2 / (P (P - 1))
* G_BLA = mean_m G_m;  s2_BLA = sum_m |G_m - G_BLA|^2 / (M (M - 1))   (``var_total``)
* s2_BLA,n = sum_m s2n_m / M^2                                         (``var_noise``)
* s2_S = M (s2_BLA - s2_BLA,n)   nonlinear variance of ONE experiment (``var_nl``)

Known reference r (closed loop): the spectra U and Y of realization m are rotated by
conj(R_m / |R_m|) (removes the random phase), averaged over periods and realizations,
G = Y_mean / U_mean, and the variances are propagated to first order with the U-Y
covariance: var(G) = (s2_Y + |G|^2 s2_U - 2 Re(conj(G) c_YU)) / |U_mean|^2, for the total
(spread over realizations) and the noise part (spread over periods) alike.

Levels (Figure 3 view): a line's level is 20 log10 of its amplitude, |DFT| * 2 / N, in the
signal's unit (dB re 1 unit peak); variances of the output are in the same scale (unit^2).
"""
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.fft

from fftune.analysis.errors import InputError

__all__ = ["BLAResult", "TransientCheck", "TransientWarning", "BLALevels",
           "detect_excited_lines", "robust_bla", "bla_levels", "to_db"]


class TransientWarning(UserWarning):
    """The periods used as steady state still contain a transient."""


def to_db(power):
    """10 log10 of a power-like quantity; None stays None, values <= 0 give NaN."""
    if power is None:
        return None
    p = np.asarray(power, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(p > 0, 10.0 * np.log10(np.where(p > 0, p, 1.0)), np.nan)


def _db_ratio(num, den):
    """10 log10(num / den) as a float, or None when undefined (missing or <= 0)."""
    if num is None or den is None or not np.isfinite(num) or not np.isfinite(den) \
            or num <= 0 or den <= 0:
        return None
    return float(10.0 * np.log10(num / den))


@dataclass
class TransientCheck:
    """Does each period look like the steady state?

    Attributes
    ----------
    level_db : ndarray, shape (T + P,)
        Mean power at the excited lines of (Y of the period - steady-state Y),
        in dB re the mean output power there.
    expected_db : ndarray or None
        Noise reference: the median level of the kept periods after the first
        (None when P < 3, where the check is not made).
    suspect : bool
        The first kept period differs from the steady state 10 dB more than the
        later periods do (needs P >= 3): a transient inside the kept periods.
    settle_differs : bool or None
        The last settle period differs from the steady state 10 dB more than the later
        periods do (expected after a start from rest; False means the settle periods
        could have been used). None without settle periods or with P < 3.
    message : str
    """

    level_db: np.ndarray
    expected_db: np.ndarray = None
    suspect: bool = False
    message: str = ""
    settle_differs: bool = None


@dataclass
class BLAResult:
    """Robust BLA estimate with its variances and the nonlinear-distortion detection.

    Attributes
    ----------
    fs : float
        Sample rate (Hz).
    n_period : int
        Samples per period N.
    bins, freq : ndarray, shape (E,)
        Excited lines: DFT bins and frequencies (Hz).
    G : ndarray of complex, shape (E,)
        G_BLA at the excited lines (output unit / input unit).
    var_total, var_noise, var_nl : ndarray, shape (E,), or None
        s2_BLA, s2_BLA,n and s2_S (docs/method.md). ``var_total`` needs M >= 2,
        ``var_noise`` P >= 2, ``var_nl`` both; ``var_nl`` may be negative where the
        noise estimate exceeds the total (kept, flagged in ``var_nl_negative``).
    var_nl_negative : ndarray of bool or None
    output_db, nl_db, noise_db : ndarray (E,) or None
        Figure 3 view at the excited lines: output level (mean over realizations of the
        period-averaged output power), nonlinear level of one experiment
        (var_nl |U|^2; NaN where var_nl < 0) and noise level of the period-averaged
        output (M var_noise |U|^2). dB re 1 unit peak.
    odd_bins, even_bins : ndarray of int
        Non-excited odd and even lines between the lowest and highest excited line.
    odd_db, even_db : ndarray
        Output level at those lines (same scale as ``output_db``).
    odd_noise_db, even_noise_db : ndarray or None
        Noise level of the period-averaged output at those lines (None when P = 1).
    summary : dict
        Power-averaged figures in dB (keys documented in docs/analysis.md); None
        where not defined.
    transient : TransientCheck
    n_realizations, n_periods, settle_periods : int
    known_reference : bool
    notes : list of str
        What could not be computed and why (M = 1, P = 1, negative variances ...).
    """

    fs: float
    n_period: int
    bins: np.ndarray
    freq: np.ndarray
    G: np.ndarray
    var_total: np.ndarray
    var_noise: np.ndarray
    var_nl: np.ndarray
    var_nl_negative: np.ndarray
    output_db: np.ndarray
    nl_db: np.ndarray
    noise_db: np.ndarray
    odd_bins: np.ndarray
    odd_db: np.ndarray
    odd_noise_db: np.ndarray
    even_bins: np.ndarray
    even_db: np.ndarray
    even_noise_db: np.ndarray
    summary: dict
    transient: TransientCheck
    n_realizations: int
    n_periods: int
    settle_periods: int
    known_reference: bool
    notes: list = field(default_factory=list)

    @property
    def odd_freq(self):
        """Frequencies (Hz) of the non-excited odd lines."""
        return self.odd_bins * self.fs / self.n_period

    @property
    def even_freq(self):
        """Frequencies (Hz) of the non-excited even lines."""
        return self.even_bins * self.fs / self.n_period


def _as_layout(name, x):
    x = np.asarray(x)
    if x.ndim != 3:
        raise InputError(f"{name}: expected an array shaped (realizations M, periods T+P, "
                         f"samples per period N), got shape {x.shape}")
    if not (np.issubdtype(x.dtype, np.floating) or np.issubdtype(x.dtype, np.integer)):
        raise InputError(f"{name}: expected real numbers, got dtype {x.dtype}")
    if x.dtype not in (np.float32, np.float64):
        x = x.astype(np.float64)
    return x


def detect_excited_lines(x, settle_periods=0, min_gap_db=10.0):
    """Find the excited lines of a periodic excitation from its spectrum.

    The power of the period-averaged spectrum (mean over realizations) at bins
    1 .. ceil(N/2) - 1 is sorted; the excited lines are those above the largest gap
    (in dB) between consecutive sorted values. Works for any grid (full, odd, odd-odd,
    random odd, user shaped) as long as excited and non-excited lines are separated.

    Parameters
    ----------
    x : array_like, shape (M, T + P, N)
        Input u (open loop) or reference r (closed loop).
    settle_periods : int
        Periods T at the start of each realization that are ignored.
    min_gap_db : float
        The gap must be at least this large (dB), else InputError.

    Returns
    -------
    ndarray of int
        Excited bins, ascending.
    """
    x = _as_layout("excitation", x)
    n = x.shape[2]
    spectrum = scipy.fft.rfft(x[:, settle_periods:, :].sum(axis=1), axis=-1)
    power = np.mean(spectrum.real ** 2 + spectrum.imag ** 2, axis=0)[1:(n + 1) // 2]
    if not np.all(np.isfinite(power)):
        raise InputError("excitation: contains NaN or inf")
    top = power.max(initial=0.0)
    if power.size < 2 or top <= 0:
        raise InputError("excitation: zero power in the input spectrum, no excited line")
    # floor at -120 dB re the largest line: rounding noise and exact zeros (float32
    # signals) must not open a larger gap than the one under the excited lines
    level = 10 * np.log10(np.maximum(power, top * 1e-12))
    order = np.sort(level)[::-1]
    gaps = order[:-1] - order[1:]
    i = int(np.argmax(gaps))
    if gaps[i] < min_gap_db:
        raise InputError(
            f"excitation: cannot tell excited from non-excited lines (largest gap in the "
            f"spectrum {gaps[i]:.1f} dB < {min_gap_db:g} dB); give the excited lines "
            f"explicitly (--lines FILE)")
    threshold = order[i] - gaps[i] / 2
    return np.flatnonzero(level > threshold) + 1


def _validate_lines(bins, n):
    bins = np.sort(np.asarray(bins, dtype=np.int64).reshape(-1))
    bins = bins[np.concatenate(([True], np.diff(bins) > 0))] if bins.size else bins
    if bins.size == 0:
        raise InputError("excited lines: none given")
    if bins[0] < 1 or bins[-1] >= (n + 1) // 2:
        raise InputError(f"excited lines: bins must lie in 1 .. {(n + 1) // 2 - 1} for "
                         f"N = {n} samples per period, got {bins[0]} .. {bins[-1]}")
    return bins


def _abs2_sum(z, axis):
    """sum |z|^2 over ``axis`` without complex temporaries (einsum on the real view)."""
    v = np.ascontiguousarray(z).view(np.float64)          # (..., 2K): re, im interleaved
    nd = v.ndim
    axis = axis % nd
    letters = "abcdefgh"[:nd]
    s = np.einsum(f"{letters},{letters}->{letters.replace(letters[axis], '')}", v, v)
    if axis == nd - 1:          # the interleaved axis itself was summed: re^2 + im^2 done
        return s
    return s[..., 0::2] + s[..., 1::2]


def _spread(z):
    """Mean over axis 1 and sum over axis 1 of |z - mean|^2."""
    mean = z.mean(axis=1)
    return mean, _abs2_sum(z - mean[:, None, :], axis=1)


def _transient(Y_exc, settle, n_periods):
    """Compare each period's output at the excited lines with the steady state.

    The steady state is the mean of the last half of the kept periods (where a
    decaying transient is smallest); the noise reference is the median deviation of the
    kept periods after the first. A decaying transient makes the first kept period
    stand out. At most 256 lines spread over the band are used.
    """
    n_total = Y_exc.shape[1]
    if Y_exc.shape[2] > 256:        # a diagnostic: 256 lines across the band are plenty
        Y_exc = Y_exc[..., np.linspace(0, Y_exc.shape[2] - 1, 256).astype(np.int64)]
    centre = Y_exc[:, n_total - max(n_periods // 2, 1):, :].mean(axis=1, keepdims=True)
    diff = Y_exc - centre
    d = _abs2_sum(diff, axis=2).mean(axis=0) / Y_exc.shape[2]          # (T+P,)
    ref = float(np.mean(np.abs(centre) ** 2))
    level = d / ref if ref > 0 else np.full_like(d, np.nan)
    check = TransientCheck(level_db=to_db(level))
    if n_periods >= 3:
        noise = float(np.median(level[settle + 1:]))
        check.expected_db = to_db(np.full(d.shape, noise))
        if settle > 0:
            last_settle = level[settle - 1]
            check.settle_differs = bool(last_settle > 10 * noise and last_settle > 1e-8)
        first = level[settle]
        if first > 10 * noise and first > 1e-8:
            check.suspect = True
            check.message = (
                f"period {settle} (the first one kept) differs from the steady state by "
                f"{10 * np.log10(first):.1f} dB re the output, the later periods by "
                f"{10 * np.log10(noise) if noise > 0 else float('-inf'):.1f} dB: transient "
                f"not over, skip more periods")
    return check


def _locate_bad(arrays):
    """After a non-finite result: which input holds NaN/inf (time domain check)."""
    for name, arr in arrays:
        if arr is not None and not np.isfinite(arr).all():
            raise InputError(f"{name}: contains NaN or inf")


def _realization_pass(u, y, r, settle, excited, det_bins):
    """Per realization: spectra at the needed lines and their reductions over periods.

    Returns a dict of arrays (unscaled DFT values): ``Y_exc`` (M, T+P, E) output at the
    excited lines; ``u_power`` (E,) sum of |U|^2; ``U_mean`` (M, E); ``det_mean``,
    ``det_ss`` (M, D) mean and sum of squared deviations over periods at the detection
    lines; known input: ``G_m``, ``G_ss`` (M, E) for G = Y/U; known reference:
    ``R_mean``, ``Un_m``, ``Yn_m`` (M, E) and ``su2``, ``sy2``, ``syu`` (M, E) the
    period sums of |dU|^2, |dY|^2, dY conj(dU) after the R/|R| rotation.
    """
    n_real, n_total, _ = y.shape
    n_exc, n_det = excited.size, det_bins.size
    y_lines = np.concatenate([excited, det_bins])
    c = np.complex128
    st = {"Y_exc": np.empty((n_real, n_total, n_exc), c), "u_power": np.zeros(n_exc),
          "U_mean": np.empty((n_real, n_exc), c), "det_mean": np.empty((n_real, n_det), c),
          "det_ss": np.empty((n_real, n_det))}
    if r is None:
        st.update(G_m=np.empty((n_real, n_exc), c), G_ss=np.empty((n_real, n_exc)))
    else:
        st.update(R_mean=np.empty((n_real, n_exc), c), Un_m=np.empty((n_real, n_exc), c),
                  Yn_m=np.empty((n_real, n_exc), c), su2=np.empty((n_real, n_exc)),
                  sy2=np.empty((n_real, n_exc)), syu=np.empty((n_real, n_exc), c))
    for m in range(n_real):
        Yl = np.take(scipy.fft.rfft(y[m], axis=-1), y_lines, axis=-1).astype(c, copy=False)
        st["Y_exc"][m] = Yl[:, :n_exc]
        Y = Yl[settle:, :n_exc]
        Yd = Yl[settle:, n_exc:]
        st["det_mean"][m], st["det_ss"][m] = _spread(Yd[None])
        U = np.take(scipy.fft.rfft(u[m, settle:], axis=-1), excited, axis=-1).astype(c, copy=False)
        st["u_power"] += _abs2_sum(U, axis=0)
        st["U_mean"][m] = U.mean(axis=0)
        if r is None:
            with np.errstate(divide="ignore", invalid="ignore"):
                G = Y / U
            st["G_m"][m], st["G_ss"][m] = _spread(G[None])
        else:
            R = np.take(scipy.fft.rfft(r[m, settle:], axis=-1), excited, axis=-1).mean(axis=0)
            st["R_mean"][m] = R
            with np.errstate(divide="ignore", invalid="ignore"):
                rot = np.conj(R / np.abs(R))
            Un, Yn = U * rot, Y * rot
            um, ss_u = _spread(Un[None])
            ym, ss_y = _spread(Yn[None])
            st["Un_m"][m], st["Yn_m"][m], st["su2"][m], st["sy2"][m] = um, ym, ss_u, ss_y
            st["syu"][m] = np.einsum("pk,pk->k", Yn - ym, np.conj(Un - um))
    return st


def robust_bla(u, y, r=None, *, fs=1.0, settle_periods=0, excited_bins=None,
               warn_transient=True):
    """Robust BLA with total, noise and nonlinear variances, and odd/even detection.

    Parameters
    ----------
    u, y : array_like, shape (M, T + P, N)
        Input and output, M realizations of T + P periods of N samples.
    r : array_like, shape (M, T + P, N), optional
        Reference (closed loop): the known-reference estimator is used.
    fs : float
        Sample rate (Hz).
    settle_periods : int
        T, periods dropped at the start of every realization.
    excited_bins : array_like of int, optional
        Excited DFT bins; found from the spectrum of r (or u) by default
        (:func:`detect_excited_lines`).
    warn_transient : bool
        Emit a :class:`TransientWarning` when the transient check is suspect.

    Returns
    -------
    BLAResult
    """
    u = _as_layout("input u", u)
    y = _as_layout("output y", y)
    if r is not None:
        r = _as_layout("reference r", r)
    for name, arr in (("output y", y), ("reference r", r)):
        if arr is not None and arr.shape != u.shape:
            raise InputError(f"{name}: shape {arr.shape} differs from input u {u.shape}")
    n_real, n_total, n = u.shape
    settle = int(settle_periods)
    if not 0 <= settle < n_total:
        raise InputError(f"settle periods T = {settle} must be in 0 .. {n_total - 1} "
                         f"(the data hold {n_total} periods per realization)")
    if n < 4:
        raise InputError(f"samples per period N = {n} is too small")
    if not np.isfinite(fs) or fs <= 0:
        raise InputError(f"fs must be a positive sample rate in Hz, got {fs}")
    n_per = n_total - settle
    excitation = r if r is not None else u
    if excited_bins is None:
        excited = detect_excited_lines(excitation, settle)
    else:
        excited = _validate_lines(excited_bins, n)

    band = np.arange(excited[0], excited[-1] + 1)
    keep = np.ones(band.size, dtype=bool)
    keep[excited - band[0]] = False
    non_exc = band[keep]
    odd_bins = non_exc[non_exc % 2 == 1]
    even_bins = non_exc[non_exc % 2 == 0]
    n_exc, n_odd = excited.size, odd_bins.size
    scale2 = (2.0 / n) ** 2        # |DFT|^2 -> squared amplitude of the line (levels only)

    def check_finite(*values):
        if not all(np.isfinite(v).all() for v in values if v is not None):
            _locate_bad((("input u", u), ("output y", y), ("reference r", r)))
            raise InputError("non-finite result (overflow in the input data?)")

    def check_power(name, power):
        # "zero" power: 120 dB or more under the median excited line (rounding noise)
        check_finite(power)
        low = np.flatnonzero(~(power > 1e-12 * np.median(power)))
        if low.size:
            raise InputError(
                f"{name}: zero power at {low.size} excited line(s) "
                f"{', '.join(f'{excited[i] * fs / n:g} Hz' for i in low[:5])}"
                f"{' ...' if low.size > 5 else ''} (wrong excited lines?)")

    # One pass over the realizations: rfft of one realization per signal, its lines
    # gathered while the spectrum is in cache, then reduced over the periods at once.
    # Only (M, lines)-sized results and the excited output lines (transient check)
    # are kept; the per-realization temporaries are reused by the allocator.
    st = _realization_pass(u, y, r, settle, excited, np.concatenate([odd_bins, even_bins]))
    check_power("input u", st["u_power"])
    if r is not None:
        check_power("reference r", np.sum(np.abs(st["R_mean"]) ** 2, axis=0))

    notes = []
    if r is None:
        G_m = st["G_m"]
        check_finite(G_m)
        G = G_m.mean(axis=0)
        var_total = var_noise = None
        if n_real >= 2:
            var_total = _abs2_sum((G_m - G)[:, None, :], axis=0)[0] / (n_real * (n_real - 1))
        if n_per >= 2:
            var_noise = st["G_ss"].sum(axis=0) / (n_per * (n_per - 1)) / n_real ** 2
        u_level = np.mean(np.abs(st["U_mean"]) ** 2, axis=0)
    else:
        U_m, Y_m = st["Un_m"], st["Yn_m"]
        U_bar, Y_bar = U_m.mean(axis=0), Y_m.mean(axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            G = Y_bar / U_bar
        check_finite(G)
        u_level = np.abs(U_bar) ** 2

        def propagate(s2y, s2u, cyu):
            return (s2y + np.abs(G) ** 2 * s2u - 2 * np.real(np.conj(G) * cyu)) / u_level

        var_total = var_noise = None
        if n_real >= 2:
            du, dy = U_m - U_bar, Y_m - Y_bar
            k = n_real * (n_real - 1)
            var_total = propagate(np.sum(np.abs(dy) ** 2, 0) / k, np.sum(np.abs(du) ** 2, 0) / k,
                                  np.sum(dy * np.conj(du), 0) / k)
        if n_per >= 2:
            k = n_per * (n_per - 1) * n_real ** 2
            var_noise = propagate(st["sy2"].sum(0) / k, st["su2"].sum(0) / k,
                                  st["syu"].sum(0) / k)

    var_nl = var_nl_negative = None
    if var_total is not None and var_noise is not None:
        var_nl = n_real * (var_total - var_noise)
        var_nl_negative = var_nl < 0
        if var_nl_negative.any():
            notes.append(f"var_nl < 0 at {int(var_nl_negative.sum())} of {excited.size} lines "
                         f"(noise estimate above the total: no detectable nonlinear "
                         f"variance there)")
    if n_real < 2:
        notes.append("M = 1 realization: no total or nonlinear variance (needs M >= 2)")
    if n_per < 2:
        notes.append("P = 1 period: no noise variance (needs P >= 2)")

    # Figure 3 view (levels as squared line amplitudes, scale2)
    Y_all_exc = st["Y_exc"]
    output_power = scale2 * np.mean(np.abs(Y_all_exc[:, settle:, :].mean(axis=1)) ** 2, axis=0)
    u_level = scale2 * u_level
    nl_power = None if var_nl is None else var_nl * u_level
    noise_power = None if var_noise is None else n_real * var_noise * u_level

    det_power = scale2 * np.mean(np.abs(st["det_mean"]) ** 2, axis=0)
    det_noise = None
    if n_per >= 2:
        det_noise = scale2 * st["det_ss"].mean(axis=0) / (n_per * (n_per - 1))
    check_finite(output_power, det_power)
    odd_power, even_power = det_power[:n_odd], det_power[n_odd:]
    odd_noise = None if det_noise is None else det_noise[:n_odd]
    even_noise = None if det_noise is None else det_noise[n_odd:]

    def mean_or_none(x):
        return None if x is None or np.size(x) == 0 else float(np.mean(x))

    out_mean = float(np.mean(output_power))
    nl_mean, noise_mean = mean_or_none(nl_power), mean_or_none(noise_power)
    odd_mean, even_mean = mean_or_none(odd_power), mean_or_none(even_power)
    odd_noise_mean, even_noise_mean = mean_or_none(odd_noise), mean_or_none(even_noise)
    summary = {
        "nl_re_output_db": _db_ratio(nl_mean, out_mean),
        "noise_re_output_db": _db_ratio(noise_mean, out_mean),
        "noise_re_nl_db": _db_ratio(noise_mean, nl_mean),
        "odd_re_output_db": _db_ratio(odd_mean, out_mean),
        "even_re_output_db": _db_ratio(even_mean, out_mean),
        "odd_re_even_db": _db_ratio(odd_mean, even_mean),
        "odd_re_noise_db": _db_ratio(odd_mean, odd_noise_mean),
        "even_re_noise_db": _db_ratio(even_mean, even_noise_mean),
        "n_var_nl_negative": None if var_nl is None else int(var_nl_negative.sum()),
    }
    # detected: power-averaged level 3 dB or more over the noise expected there
    summary["odd_detected"] = (None if summary["odd_re_noise_db"] is None
                               else summary["odd_re_noise_db"] > 3.0)
    summary["even_detected"] = (None if summary["even_re_noise_db"] is None
                                else summary["even_re_noise_db"] > 3.0)

    transient = _transient(Y_all_exc, settle, n_per)
    if transient.suspect:
        notes.append(transient.message)
        if warn_transient:
            warnings.warn(transient.message, TransientWarning, stacklevel=2)

    return BLAResult(
        fs=float(fs), n_period=n, bins=excited, freq=excited * fs / n, G=G,
        var_total=var_total, var_noise=var_noise, var_nl=var_nl,
        var_nl_negative=var_nl_negative, output_db=to_db(output_power),
        nl_db=to_db(nl_power), noise_db=to_db(noise_power),
        odd_bins=odd_bins, odd_db=to_db(odd_power), odd_noise_db=to_db(odd_noise),
        even_bins=even_bins, even_db=to_db(even_power), even_noise_db=to_db(even_noise),
        summary=summary, transient=transient, n_realizations=n_real, n_periods=n_per,
        settle_periods=settle, known_reference=r is not None, notes=notes)


@dataclass
class BLALevels:
    """Robust BLA at several excitation levels (the paper's Figure 4).

    Attributes
    ----------
    rms : ndarray, shape (L,)
        rms of the excitation (input u, or r if given) per level, steady periods.
    results : list of BLAResult
    freq : ndarray, shape (E,)
        Excited frequencies (Hz), common to all levels.
    G : ndarray of complex, shape (L, E)
    """

    rms: np.ndarray
    results: list
    freq: np.ndarray
    G: np.ndarray


def bla_levels(u_levels, y_levels, r_levels=None, **kwargs):
    """:func:`robust_bla` at each of L excitation levels.

    Parameters
    ----------
    u_levels, y_levels : sequence of array_like, each (M, T + P, N)
    r_levels : sequence of array_like, optional
    **kwargs
        Passed to :func:`robust_bla` (fs, settle_periods, excited_bins ...).

    Returns
    -------
    BLALevels
    """
    if len(u_levels) != len(y_levels) or (r_levels is not None and len(r_levels) != len(u_levels)):
        raise InputError("bla_levels: u, y (and r) need the same number of levels")
    results, rms = [], []
    settle = int(kwargs.get("settle_periods", 0))
    for i in range(len(u_levels)):
        r = None if r_levels is None else r_levels[i]
        res = robust_bla(u_levels[i], y_levels[i], r, **kwargs)
        exc = np.asarray(r if r is not None else u_levels[i])[:, settle:, :]
        rms.append(float(np.sqrt(np.mean(np.square(exc, dtype=float)))))
        results.append(res)
    if any(not np.array_equal(res.bins, results[0].bins) for res in results):
        raise InputError("bla_levels: the excited lines differ between levels")
    return BLALevels(rms=np.array(rms), results=results, freq=results[0].freq,
                     G=np.stack([res.G for res in results]))
