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

from fftune.analysis.checks import check_arguments, check_blocks
from fftune.analysis.errors import InputError

__all__ = ["BLAResult", "TransientCheck", "TransientWarning", "BLALevels",
           "detect_excited_lines", "robust_bla", "robust_bla_spectra", "robust_bla_moments",
           "LineMoments", "bla_levels", "robust_bla_mimo", "MimoBLAResult",
           "classify_grid", "level_verdict", "estimate_quantisation_step", "to_db"]


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
        Only for grids that separate odd from even distortion (odd bins excited, see
        :func:`classify_grid`); empty otherwise.
    odd_noise_db, even_noise_db : ndarray or None
        Noise level of the period-averaged output at those lines (None when P = 1).
    grid : str
        Excitation grid (:func:`classify_grid`).
    nonexcited_bins, nonexcited_db, nonexcited_noise_db : ndarray
        Every non-excited line in the band (whatever the grid), its output level and
        noise level.
    plant_db : ndarray or None
        Plant-referred level at the non-excited lines: output minus the BLA
        (interpolated) times the input measured there, period-averaged (same scale).
    plant_expected_db : ndarray or None
        What ``plant_db`` holds without plant distortion: its noise plus the BLA
        interpolation error (leave-one-out) times the input there.
    quantisation_floor_db : float or None
        Output quantisation level per line (power mean over the non-excited lines of
        ``quantisation_db``), given ``y_quantisation_step``.
    quantisation_db : ndarray or None
        Expected quantisation error at each non-excited line (same scale): the
        deterministic error of quantising the predicted periodic output (docs/analysis.md),
        or the white floor 4 (q^2/12) / N without the samples.
    summary : dict
        Per-line medians, power ratios, detection flags, plant-referred figures (keys
        documented in docs/analysis.md); None where not defined.
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
    grid: str = None
    nonexcited_bins: np.ndarray = None
    nonexcited_db: np.ndarray = None
    nonexcited_noise_db: np.ndarray = None
    plant_db: np.ndarray = None
    plant_expected_db: np.ndarray = None
    quantisation_floor_db: float = None
    quantisation_db: np.ndarray = None

    def to_frd(self):
        """The BLA as a python-control frequency response data model.

        Returns
        -------
        control.FrequencyResponseData
            ``control.frd(G, 2 pi freq)``: G_BLA at the excited lines, frequencies in
            rad/s (python-control's unit). python-control is optional (``pip install
            control``), imported here only. Its FRD has no field for an estimate's
            variance: ``var_total`` and ``var_noise`` (arrays over the same lines, or None)
            ride along as attributes of the returned object (FRD arithmetic drops them;
            :mod:`fftune.analysis.frf_export` writes them for MATLAB).

        Raises
        ------
        ImportError
            python-control is not installed (the message says how to install it).
        """
        try:
            import control
        except ImportError:
            raise ImportError("BLAResult.to_frd needs python-control, which is not installed "
                              "(pip install control)") from None
        frd = control.frd(np.asarray(self.G, dtype=complex), 2 * np.pi * np.asarray(self.freq))
        frd.var_total, frd.var_noise = self.var_total, self.var_noise
        return frd

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


def _split_by_gap(level, min_lower):
    """Largest gap between consecutive sorted values (descending) that leaves at least
    ``min_lower`` values below it; returns (threshold, gap) or (None, 0)."""
    order = np.sort(level)[::-1]
    gaps = order[:-1] - order[1:]
    # split after position i: lower cluster holds order.size - 1 - i values
    allowed = np.arange(gaps.size) <= order.size - 1 - min_lower
    if not allowed.any():
        return None, 0.0
    gaps = np.where(allowed, gaps, -np.inf)
    i = int(np.argmax(gaps))
    return order[i] - gaps[i] / 2, float(gaps[i])


def _local_floor(level, half_width=24, quantile=0.1):
    """Low quantile of ``level`` in a window of +-half_width lines (the non-excited floor
    near each line when the excited lines are fewer than 90 % of the window)."""
    from numpy.lib.stride_tricks import sliding_window_view
    padded = np.pad(level, half_width, mode="reflect")
    return np.quantile(sliding_window_view(padded, 2 * half_width + 1), quantile, axis=-1)


def _otsu(values):
    """Otsu threshold of 1-D values: the split of the sorted values that maximises the
    between-class variance; returns (threshold, upper median - lower median)."""
    v = np.sort(values)
    n = v.size
    c = np.cumsum(v)
    k = np.arange(1, n)                     # lower class = v[:k]
    mu_lo = c[:-1] / k
    mu_hi = (c[-1] - c[:-1]) / (n - k)
    score = k * (n - k) * (mu_hi - mu_lo) ** 2
    i = int(np.argmax(score)) + 1
    return (v[i - 1] + v[i]) / 2, float(np.median(v[i:]) - np.median(v[:i]))


def detect_excited_lines(x, settle_periods=0, min_gap_db=10.0, return_info=False,
                         _spectrum=None):
    """Find the excited lines of a periodic excitation from its spectrum.

    The power of the period-averaged spectrum (mean over realizations) at bins
    1 .. ceil(N/2) - 1 is taken in dB, and the excited lines are the cluster far above
    the rest:

    1. the largest gap between consecutive sorted levels (full, odd, odd-odd, random odd
       grids with excited lines at similar levels), if it is at least ``min_gap_db``;
    2. otherwise (a distorted input: the excited level and a broadband distortion vary
       over the band and their scatter fills the gap) the level re a running floor (10th
       percentile of +-24 lines) split at its Otsu threshold, if the two clusters' medians
       lie at least 2 ``min_gap_db`` apart and at most 5 % of the lines fall within 3 dB of
       the threshold.

    A split must leave at least max(2, 1 %) of the lines below it: a few near-zero lines
    (a filter's stop band, float32 zeros) never make "every other line excited".

    Parameters
    ----------
    x : array_like, shape (M, T + P, N)
        Input u (open loop) or reference r (closed loop).
    settle_periods : int
        Periods T at the start of each realization that are ignored.
    min_gap_db : float
        Separation needed (dB), else InputError.
    return_info : bool
        Also return a dict: ``method`` ('gap' or 'local threshold'), ``separation_db``,
        ``note`` (None, or what the caller should tell the user).

    Returns
    -------
    ndarray of int
        Excited bins, ascending (and the info dict with ``return_info``).
    """
    x = _as_layout("excitation", x)
    n = x.shape[2]
    # (_spectrum: that of the period sums, computed by the caller's checks already)
    spectrum = (np.fft.rfft(x[:, settle_periods:, :].sum(axis=1), axis=-1)
                if _spectrum is None else _spectrum)
    k_max = (n + 1) // 2
    if spectrum.dtype == np.complex128:
        v = spectrum[:, 1:k_max].view(np.float64)
        s = np.einsum("mk,mk->k", v, v)                  # sum over m of re^2, im^2
        power = (s[0::2] + s[1::2]) / spectrum.shape[0]
    else:                                                # (float32 records: as computed)
        power = np.mean(spectrum.real ** 2 + spectrum.imag ** 2, axis=0)[1:k_max]
    if not np.all(np.isfinite(power)):
        raise InputError("excitation: contains NaN or inf")
    top = power.max(initial=0.0)
    if power.size < 2 or top <= 0:
        raise InputError("excitation: zero power in the input spectrum, no excited line")
    # floor at -120 dB re the largest line: rounding noise and exact zeros (float32
    # signals) must not open a larger gap than the one under the excited lines
    level = 10 * np.log10(np.maximum(power, top * 1e-12))
    min_lower = max(2, int(np.ceil(0.01 * level.size)))
    threshold, gap = _split_by_gap(level, min_lower)
    info = {"method": "gap", "separation_db": gap, "note": None}
    found = None
    if threshold is not None and gap >= min_gap_db:
        found = np.flatnonzero(level > threshold) + 1
        found = _refine_in_band(level, found, min_gap_db)
    elif level.size >= 64:
        rel = level - _local_floor(level)
        thr, sep = _otsu(rel)
        ambiguous = float(np.mean(np.abs(rel - thr) < 3.0))
        if sep >= 2 * min_gap_db and ambiguous <= 0.05:
            found = np.flatnonzero(rel > thr) + 1
            info = {"method": "local threshold", "separation_db": sep,
                    "note": f"excited lines found by a threshold on the level re the local "
                            f"floor (no clean gap in the spectrum: the input is distorted); "
                            f"{100 * ambiguous:.1f} % of the lines lie within 3 dB of the "
                            f"threshold: give the design's lines (--lines FILE) to be sure"}
    if found is None:
        raise InputError(
            f"excitation: cannot tell excited from non-excited lines (largest gap in the "
            f"spectrum {gap:.1f} dB < {min_gap_db:g} dB, no clear cluster re the local "
            f"floor either); give the excited lines explicitly (excited_bins, CLI --lines)")
    found, strays = _stray_lines(level, found)
    info["stray_bins"] = strays
    # how sure: the margin between the weakest excited line and the strongest other line
    # of the band, both re the excited lines' local level
    inband = np.arange(found[0], found[-1] + 1)
    is_found = np.zeros(inband.size, bool)
    is_found[found - found[0]] = True
    is_other = ~is_found
    is_other[strays[(strays >= found[0]) & (strays <= found[-1])] - found[0]] = False
    margin = None
    if is_other.any():
        ref = np.interp(inband, found, level[found - 1])
        rel = level[inband - 1] - ref
        margin = float(np.min(rel[is_found]) - np.max(rel[is_other]))
    info["margin_db"] = margin
    info["confidence"] = ("clear" if margin is None or margin >= 20.0 else
                          "fair" if margin >= min_gap_db else "weak")
    if strays.size:
        lv = level[strays - 1] - np.median(level[found - 1])
        strays_note = (f"{strays.size} input line(s) off the excitation grid left out of the "
                       f"excited and the detection lines (stray tones: "
                       + ", ".join(f"bin {b} at {v:+.0f} dB" for b, v in zip(strays[:5], lv[:5]))
                       + (" ..." if strays.size > 5 else "") + " re the median excited line)")
        info["note"] = strays_note if info["note"] is None else info["note"] + "; " + strays_note
    if info["confidence"] == "weak" and info["note"] is None:
        info["note"] = (f"excited lines found with a weak margin ({margin:.1f} dB between the "
                        f"weakest excited and the strongest other line of the band): give the "
                        f"design's lines (--lines FILE) to be sure")
    return (found, info) if return_info else found


def _refine_in_band(level, found, min_gap_db):
    """The largest gap of the whole spectrum can be a filter's stop band (a band-limited
    record whose out-of-band floor lies far under the in-band distortion) or the zeros
    of an odd grid's even lines under the distortion of a distorted input: split the
    lines found again while their own levels show a gap of ``min_gap_db`` and the lines
    split off lie among the kept ones (max(2, 5 %) of them inside the kept band: the
    level of the non-excited lines), or beside them at a level 40 dB or more down or
    scattering line to line by more than 2 dB (median), like distortion; a smooth step
    beside the band is a designed amplitude step and stays."""
    for _ in range(6):
        if found.size < 8:
            break
        lv = level[found - 1]
        thr, gap = _split_by_gap(lv, max(2, int(np.ceil(0.01 * found.size))))
        if thr is None or gap < min_gap_db:
            break
        new = found[lv > thr]
        dropped = found[lv <= thr]
        if new.size < 2:
            break
        inside = int(np.sum((dropped > new[0]) & (dropped < new[-1])))
        # lines only beside the kept band: a designed amplitude step (smooth, within
        # 40 dB) stays excited; a level that scatters line to line like noise or lies
        # 40 dB or more down is distortion (a full grid's band-limited force)
        lv_d = level[dropped - 1]
        scatter = float(np.median(np.abs(np.diff(lv_d)))) if dropped.size >= 8 else 0.0
        if inside < max(2, 0.05 * new.size) and gap < 40.0 and scatter < 2.0:
            break
        found = new
    return found


def _stray_lines(level, found):
    """Lines of ``found`` that do not belong to the excitation: a handful (at most
    max(2, 2 %)) off the grid's parity pattern (even lines among odd ones, 4k+3 among
    4k+1), or 6 dB or more under the median of their 5 nearest excited neighbours on
    each side (both sides: a line at a designed amplitude step follows one of them).
    Returns (excited, strays)."""
    empty = np.array([], dtype=np.int64)
    if found.size < 20:
        return found, empty
    allow = max(2, int(0.02 * found.size))
    stray = np.zeros(found.size, dtype=bool)
    odd = found % 2 == 1
    if 0 < np.sum(~odd) <= allow:
        stray |= ~odd
    elif 0 < np.sum(odd) <= allow:
        stray |= odd
    keep = ~stray
    r1 = (found % 4 == 1) & keep & odd
    r3 = (found % 4 == 3) & keep & odd
    if np.all(odd[keep]):
        if 0 < r3.sum() <= allow < r1.sum():
            stray |= r3
        elif 0 < r1.sum() <= allow < r3.sum():
            stray |= r1
    idx = np.flatnonzero(~stray)
    lv = level[found[idx] - 1]
    if idx.size >= 21:
        # a line 6 dB under the median of its 10 nearest neighbours in the set: only lines
        # 6 dB under the set's largest level can be (the few others are not computed)
        cand = np.flatnonzero(lv < lv.max() - 6.0)
        padded = np.concatenate((lv[5:0:-1], lv, lv[-2:-7:-1]))     # np.pad(lv, 5, "reflect")
        # (median of 5: the third order statistic)
        left = np.partition(padded[cand[:, None] + np.arange(5)], 2, axis=1)[:, 2]
        right = np.partition(padded[cand[:, None] + np.arange(6, 11)], 2, axis=1)[:, 2]
        # under BOTH sides: a line at a designed amplitude step is level with one side
        low = cand[lv[cand] < np.minimum(left, right) - 6.0]
        if 0 < low.size <= allow:
            stray[idx[low]] = True
    return found[~stray], found[stray]


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


def _in_band(band, bins):
    """np.isin(band, bins) for a contiguous band (consecutive bins) that holds every one
    of the sorted ``bins`` (the excited lines of their own band): an index, no search."""
    if band.size and band[-1] - band[0] == band.size - 1 and np.size(bins) \
            and bins[0] >= band[0] and bins[-1] <= band[-1]:
        mask = np.zeros(band.size, dtype=bool)
        mask[np.asarray(bins) - band[0]] = True
        return mask
    return np.isin(band, bins)


def _mean0(x):
    """Mean over axis 0 (np.mean's sum / count without its Python-level overhead)."""
    return np.add.reduce(x, axis=0) / x.shape[0]


def _median(a):
    """np.median of all values (NaN if any is NaN), without np.median's Python-level
    overhead (called for many small arrays per estimate)."""
    a = np.asarray(a, dtype=float).reshape(-1)
    n = a.size
    if n == 0:
        return np.median(a)          # nan and numpy's warning, as before
    if np.isnan(a).any():
        return np.float64(np.nan)
    k = (n - 1) // 2
    if n % 2:
        return np.partition(a, k)[k]
    part = np.partition(a, (k, k + 1))
    return (part[k] + part[k + 1]) / 2.0


def _abs2(z):
    """|z|^2 elementwise, as re^2 + im^2 (no hypot and square root)."""
    z = np.asarray(z)
    return z.real ** 2 + z.imag ** 2 if np.iscomplexobj(z) else z * z


def _spread2_inplace(z):
    """Mean over axis 0 of a (P, K) complex128 array whose rows are contiguous, and the
    sum over axis 0 of |z - mean|^2; z is overwritten with its deviations z - mean (no
    temporary of z's size: the sums read its real view)."""
    if z.strides[-1] != z.itemsize:      # (e.g. a fancy index's column-major result)
        zc = np.ascontiguousarray(z)
        mean, ss = _spread2_inplace(zc)
        z[...] = zc
        return mean, ss
    mean = np.add.reduce(z, axis=0) / z.shape[0]
    z -= mean
    v = z.view(np.float64)                                # (P, 2K): re, im interleaved
    s = np.einsum("pk,pk->k", v, v)
    return mean, s[0::2] + s[1::2]


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
    tail = Y_exc[:, n_total - max(n_periods // 2, 1):, :]
    centre = np.add.reduce(tail, axis=1, keepdims=True) / tail.shape[1]
    diff = Y_exc - centre
    d = _mean0(_abs2_sum(diff, axis=2)) / Y_exc.shape[2]          # (T+P,)
    ref = float(np.add.reduce(_abs2(centre), axis=None) / centre.size)
    level = d / ref if ref > 0 else np.full_like(d, np.nan)
    check = TransientCheck(level_db=to_db(level))
    if n_periods >= 3:
        noise = float(_median(level[settle + 1:]))
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


def _locate_bad(arrays, fs=None):
    """After a non-finite result: which input holds NaN/inf and where (time domain)."""
    from fftune.analysis.checks import locate_nonfinite
    for name, arr in arrays:
        if arr is not None:
            text = locate_nonfinite(name, arr, fs=fs)
            if text:
                raise InputError(text)


def classify_grid(excited_bins, n_period):
    """What the excitation grid lets the non-excited lines say.

    Parameters
    ----------
    excited_bins : array_like of int
        Excited DFT bins, ascending.
    n_period : int
        Samples per period N (bins 1 .. ceil(N/2) - 1 are usable).

    Returns
    -------
    dict
        ``grid``: 'random odd' (odd bins, some odd bins of the band left out), 'odd'
        (every odd bin of the band), 'odd-odd' (bins 4k+1 only, or 4k+3 only),
        'full' (both parities, no line left out), 'full with removed lines' (both
        parities, some lines left out), 'even' (even bins only); ``parity`` True when
        odd and even nonlinear distortions fall on separate non-excited lines (odd
        grids: an odd number of odd bins sums to an odd bin, an even number to an even
        bin); ``note``: why there is no parity claim (None when there is).
    """
    exc = np.asarray(excited_bins, dtype=np.int64).reshape(-1)
    if exc.size > 1 and not np.all(exc[1:] > exc[:-1]):     # (sorted and unique: as is)
        exc = np.unique(exc)
    band = np.arange(exc[0], exc[-1] + 1)
    keep = np.ones(band.size, bool)
    keep[exc - exc[0]] = False
    removed = band[keep]
    if np.all(exc % 2 == 1):
        if exc.size > 1 and np.all(exc % 4 == exc[0] % 4):
            grid = "odd-odd"
        elif np.any(removed % 2 == 1):
            grid = "random odd"
        else:
            grid = "odd"
        return {"grid": grid, "parity": True, "note": None}
    if np.all(exc % 2 == 0):
        return {"grid": "even", "parity": False,
                "note": "even bins only: odd and even nonlinear distortions both fall on "
                        "even bins; only 'nonlinear' can be said, no odd/even claim"}
    if removed.size == 0:
        return {"grid": "full", "parity": False,
                "note": "full grid: every line of the band is excited, no non-excited line: "
                        "nonlinear distortion is judged at the excited lines only (var_total "
                        "vs var_noise, needs M >= 2 and P >= 2), without an odd/even split "
                        "(design a random odd multisine for that)"}
    return {"grid": "full with removed lines", "parity": False,
            "note": "full grid with removed lines: odd and even distortions both fall on "
                    "every line (odd + even bins mix), so the removed lines say only "
                    "'nonlinear', not odd or even (use a random odd multisine for that)"}


def _unwrap(p):
    """np.unwrap(p) of a 1-D phase (rad): the same arithmetic without its general-axis
    overhead (called once per estimate on the excited lines)."""
    if p.size < 2:
        return p.copy()
    dd = p[1:] - p[:-1]
    ddmod = np.mod(dd + np.pi, 2 * np.pi) - np.pi
    np.copyto(ddmod, np.pi, where=(ddmod == -np.pi) & (dd > 0))
    correct = ddmod - dd
    np.copyto(correct, 0.0, where=np.abs(dd) < np.pi)
    out = p.copy()
    out[1:] += np.cumsum(correct)
    return out


def _lagrange4(xs, xa, values):
    """4-point Lagrange interpolation: ``xs`` (4, n) nodes, ``xa`` (n,) abscissae,
    ``values`` (4, n) at the nodes; weight j = prod over i != j of (xa - x_i) / (x_j - x_i)
    (the factors in the order of i), column by column (no reductions over an axis of 4)."""
    d = [xa - xs[i] for i in range(4)]
    total = None
    with np.errstate(divide="ignore", invalid="ignore"):
        for j in range(4):
            w = None
            for i in range(4):
                if i != j:
                    q = d[i] / (xs[j] - xs[i])
                    w = q if w is None else w * q
            term = w * values[j]
            total = term if total is None else total + term
    return total


def _interp_frf(freq, G, f_at):
    """G at ``f_at`` from 4-point Lagrange interpolation in log f of log|G| and the
    unwrapped phase (exact for power laws such as a double integrator); and the
    relative leave-one-out error at each excited line (each line predicted from its two
    neighbours on each side), an upper bound of the error at the lines in between."""
    e = freq.size
    x = np.log(freq)
    logmag = np.log(np.maximum(np.abs(G), 1e-300))
    phase = _unwrap(np.angle(G))
    if e < 5:
        g_at = np.exp(np.interp(np.log(f_at), x, logmag) + 1j * np.interp(np.log(f_at), x, phase))
        return g_at, np.full(e, np.inf)
    logg = logmag + 1j * phase          # one interpolation for both (the same weights)

    def predict(idx, xa):               # idx (4, n): the nodes of each abscissa
        return np.exp(_lagrange4(x[idx], xa, logg[idx]))

    xa = np.log(np.asarray(f_at, dtype=float))
    start = np.clip(np.searchsorted(x, xa) - 2, 0, e - 4)
    g_at = predict(start + np.arange(4)[:, None], xa)
    # leave one out: window of 4 among the other e - 1 lines, centred on line i
    i = np.arange(e)
    start = np.clip(i - 2, 0, e - 5)
    reduced = start + np.arange(4)[:, None]
    idx = reduced + (reduced >= i)
    loo = predict(idx, x)
    return g_at, np.abs(loo - G) / np.abs(G)


def _binom_sf_counts(n_lines, p_line):
    """P(Binomial(n_lines, p_line) >= k) for k = 0 .. n_lines (numpy only: no scipy.stats
    import on the first call)."""
    k = np.arange(n_lines + 1)
    logs = np.log(np.arange(1, n_lines + 1, dtype=float))
    log_fact = np.concatenate(([0.0], np.cumsum(logs)))
    p = min(max(float(p_line), 1e-300), 1.0 - 1e-16)
    log_pmf = (log_fact[-1] - log_fact - log_fact[::-1] + k * np.log(p)
               + (n_lines - k) * np.log1p(-p))
    pmf = np.exp(log_pmf - log_pmf.max())
    pmf /= pmf.sum()
    return np.minimum(np.cumsum(pmf[::-1])[::-1], 1.0)


def _false_alarm_count(n_lines, p_line, alpha=1e-3):
    """Smallest count k >= 1 with P(Binomial(n_lines, p_line) >= k) <= alpha."""
    if n_lines == 0:
        return None
    p = float(p_line)
    if 0.0 < p < 1.0 and n_lines * p < 300 and alpha >= 1e-12:
        # the cdf term by term up to 1 - alpha, pmf(k + 1) = pmf(k) (n - k) / (k + 1) p / (1 - p)
        # (1 - alpha in float64 carries alpha to 1e-4 of itself down to 1e-12; a smaller alpha
        # takes the exact tail below)
        # (cumprod and cumsum: the same sequence of products and sums as a loop; the terms
        # past the mean + 12 sd + 40 are not reached for alpha >= 1e-30)
        r = p / (1.0 - p)
        stop = int(min(n_lines, n_lines * p + 12.0 * np.sqrt(n_lines * p) + 40.0))
        k = np.arange(stop, dtype=float)
        steps = np.empty(stop + 1)
        steps[0] = (1.0 - p) ** n_lines
        steps[1:] = (n_lines - k) / (k + 1) * r
        cdf = np.cumsum(np.cumprod(steps))
        reached = np.flatnonzero(cdf >= 1.0 - alpha)
        if reached.size:
            return max(1, int(reached[0]) + 1)
        # (not reached, a rounding of the sum: the exact tail below)
    sf = _binom_sf_counts(n_lines, p_line)
    ok = np.flatnonzero(sf <= alpha)
    return max(1, int(ok[0]) if ok.size else n_lines + 1)


def f_sf_even(x, d1, d2):
    """Tail P(F > x) of Fisher's F(d1, d2) for an even numerator d1 (d2 > 0 real): the
    finite sum of the regularized incomplete beta function, numpy only.

    With w = d1 x / (d2 + d1 x), a = d1 / 2, b = d2 / 2:
    P(F > x) = (1 - w)^b sum_{j < a} Gamma(b + j) / (Gamma(b) j!) w^j.
    """
    import math
    a, b = int(d1) // 2, float(d2) / 2.0
    x = np.maximum(np.asarray(x, dtype=float), 0.0)
    w = d1 * x / (d2 + d1 * x)
    with np.errstate(divide="ignore"):
        log1mw = np.log1p(-np.minimum(w, 1.0))
        logw = np.log(w)
    if a == 0:
        return np.minimum(np.zeros_like(w), 1.0)
    # all a terms at once, (a, ...) then summed over j in order
    j = np.arange(a, dtype=float).reshape((a,) + (1,) * w.ndim)
    coef = np.array([math.lgamma(b + i) - math.lgamma(b) - math.lgamma(i + 1) for i in range(a)])
    coef = coef.reshape(j.shape)
    with np.errstate(invalid="ignore"):
        jlogw = j * logw
    jlogw[0] = 0.0                      # (j = 0: w^0 = 1, also where log w = -inf)
    term = coef + b * log1mw + jlogw
    total = np.add.accumulate(np.exp(np.where(np.isfinite(term), term, -np.inf)), axis=0)[-1]
    return np.minimum(total, 1.0)


def _class_stats(level, reference, nu, prefix, alpha=1e-3, tail=None, known=None,
                 known_margin=8.0):
    """Per-line figures of one class of non-excited lines (level vs what is expected
    there without nonlinear distortion, ``reference``).

    A noise-only line exceeds x times its estimated noise with probability
    (1 + x / nu)^-nu (F(2, 2 nu) tail, nu = M (P - 1) complex degrees of freedom of the
    noise estimate). The class is detected when more lines lie 6 dB over than noise
    gives with probability ``alpha`` (binomial), or when the most significant line alone
    is (Bonferroni: n min p <= alpha): a few lines far above the noise count as much as
    many lines a little above it. Returns the median excess (dB), the count 6 dB over,
    the count needed, the count noise gives on average, and the flag (None without a
    line or a reference). ``tail(ratio)``: the probability that a noise-only line exceeds
    ``ratio`` times its reference (default the F(2, 2 nu) tail above). ``known``: a
    part of ``reference`` that is a model, not a noise estimate (the quantisation error):
    the strongest line's probability is then that of its excess over ``known_margin``
    times it, relative to the noise part: (level - margin known) / (reference - known).
    """
    out = {f"{prefix}lines": int(np.size(level))}
    if level is None or np.size(level) == 0 or reference is None or nu < 1:
        out.update({f"{prefix}line_median_re_noise_db": None, f"{prefix}lines_over_noise_6db": None,
                    f"{prefix}lines_needed": None, f"{prefix}lines_by_noise": None,
                    f"{prefix}detected": None})
        return out
    if tail is None:
        def tail(x):
            return (1.0 + np.maximum(x, 0) / nu) ** (-nu)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = level / reference
        if known is not None:
            thr = known_margin * known
            tested = level > thr
            ex = np.maximum(level - thr, 0.0) / np.maximum(reference - known, 1e-300)
        else:
            tested = ratio > 0
            ex = ratio
        # the smallest line probability: the tail falls with the ratio, so it is the tail
        # at the largest finite ratio (and at inf, where f_sf_even gives NaN, ignored as
        # np.nanmin would); untested lines have probability 1
        ex = ex[tested]
        finite = ex[np.isfinite(ex)]
        candidates = [finite.max()] if finite.size else []
        if finite.size < ex.size and np.isinf(ex).any():
            candidates.append(np.inf)
        p_min = np.asarray(tail(np.array(candidates, dtype=float))) if candidates else np.empty(0)
        if ex.size < level.size:
            p_min = np.append(p_min, 1.0)
        # median of 10 log10(ratio): log10 keeps the order, so only the middle values
        med = np.nan
        if not (np.isnan(ratio).any() or (ratio < 0).any()):
            k = (ratio.size - 1) // 2
            mid = np.partition(ratio, (k, k + 1) if ratio.size % 2 == 0 else k)
            med = (10 * np.log10(mid[k]) if ratio.size % 2 else
                   (10 * np.log10(mid[k]) + 10 * np.log10(mid[k + 1])) / 2.0)
        med = float(med)
    p_line = float(tail(np.array(4.0)))
    over = int(np.sum(level > 4.0 * reference))
    need = _false_alarm_count(level.size, p_line, alpha)
    strongest = bool(p_min.size and level.size * np.nanmin(p_min) <= alpha)
    out.update({f"{prefix}line_median_re_noise_db": med if np.isfinite(med) else None,
                f"{prefix}lines_over_noise_6db": over, f"{prefix}lines_needed": need,
                f"{prefix}lines_by_noise": float(level.size * p_line),
                f"{prefix}detected": bool(over >= need or strongest)})
    return out


def _running_mean(x, half_width):
    """Mean of x over a window of +-half_width values (shrunk at the ends)."""
    c = np.concatenate(([0.0], np.cumsum(x)))
    i = np.arange(x.size)
    lo, hi = np.maximum(i - half_width, 0), np.minimum(i + half_width + 1, x.size)
    return (c[hi] - c[lo]) / (hi - lo)


def quantisation_error_lines(s, q, sigma, bins):
    """Deterministic quantisation error of a periodic signal at DFT lines.

    Quantising a periodic signal s (one period, no noise) gives an error e = q round(s/q) - s
    that is periodic too, so it sits on the harmonic lines of the period, and odd-symmetric
    in s (an odd nonlinearity of the signal): not white noise. Gaussian noise of standard
    deviation ``sigma`` before the quantiser dithers it: the mean error over periods is the
    sawtooth's Fourier series with each harmonic k damped by exp(-2 (pi k sigma / q)^2).

    Parameters
    ----------
    s : ndarray, shape (..., N)
        One period of the noise-free signal (unit of y).
    q : float
        Quantisation step.
    sigma : float
        Standard deviation of the noise before the quantiser (unit of y).
    bins : array_like of int
        DFT bins to return.

    Returns
    -------
    ndarray of complex, shape (..., len(bins))
        rfft of the mean error (numpy scaling, no 1/N) at ``bins``.
    """
    e = _mean_quantisation_error(s, q, sigma)
    return np.take(np.fft.rfft(e, axis=-1), np.asarray(bins), axis=-1)


def _mean_quantisation_error(s, q, sigma):
    """E[q round((s + n) / q)] - s for Gaussian n of standard deviation sigma."""
    if sigma < 0.05 * q:
        return q * np.round(s / q) - s
    k_max = max(1, int(np.ceil(0.7 * q / sigma)))
    e = np.zeros_like(s)
    phase = 2 * np.pi * s / q
    for k in range(1, k_max + 1):
        e += (q / (np.pi * k)) * (-1) ** k * np.exp(-2 * (np.pi * k * sigma / q) ** 2) \
            * np.sin(k * phase)
    return e


def _quantisation_lines(q, y_mean_time, mom, *, is_exc, det_i, g_det, n, n_per, scale2):
    """Expected quantisation power at the detection lines (level scale, per line).

    The deterministic error of quantising the noise-free periodic output
    (:func:`quantisation_error_lines`), simulated on the output predicted from the
    measurement: the period-averaged output at the excited lines plus the BLA times the
    input at the detection lines (the linear part, without the distortion and the
    quantisation error that the measurement holds there), dithered by the measured noise.
    With the samples (``y_mean_time``) the offset within a step is fitted to them; without
    (line moments) the power is averaged over offsets. The simulated error matches the
    measured one in level, not line by line (the prediction is not the exact signal), so
    its running mean over +-8 detection lines of the same parity, doubled, is taken, but
    not less than the simulated line itself. The random part of a dithered quantisation
    is in the noise estimate already."""
    band = mom.bins
    S = np.zeros((mom.Y.shape[0], n // 2 + 1), np.complex128)
    if y_mean_time is not None:
        Yf = np.fft.rfft(np.asarray(y_mean_time, dtype=np.float64), axis=-1)
        S[:, 0] = Yf[:, 0]
    S[:, band[is_exc]] = mom.Y[:, np.flatnonzero(is_exc)]
    if g_det is not None:
        S[:, band[det_i]] = g_det * mom.U[:, det_i]
    smooth = np.fft.irfft(S, n=n, axis=-1)
    sigma2 = 0.0
    if n_per >= 2:
        # white noise: a line's period-to-period variance is N sigma^2
        sigma2 = float(_median(mom.ss_y[:, det_i]) / (n_per - 1) / n)
    sigma = float(np.sqrt(max(sigma2 - q ** 2 / 12.0, 0.0)))
    # The predicted output's offset within a step decides the error's symmetry (odd vs
    # even lines) and is not known to better than q: per realization, the offset whose
    # quantised prediction reproduces the measured period mean best is taken; without the
    # samples (line moments: no DC, no time signal) the power is averaged over offsets
    if y_mean_time is not None:
        y_mean = np.asarray(y_mean_time, dtype=np.float64)
        best = np.full(smooth.shape[0], np.inf)
        shift = np.zeros(smooth.shape[0])
        for c in np.linspace(-0.5 * q, 0.5 * q, 21):
            sc = smooth + c
            err = np.sum((sc + _mean_quantisation_error(sc, q, sigma) - y_mean) ** 2, axis=-1)
            better = err < best
            best[better], shift[better] = err[better], c
        D = quantisation_error_lines(smooth + shift[:, None], q, sigma, band[det_i])
        power = scale2 * _mean0(_abs2(D))
    else:
        power = np.zeros(det_i.size)
        offsets = np.linspace(-0.5 * q, 0.5 * q, 8, endpoint=False)
        for c in offsets:
            D = quantisation_error_lines(smooth + c, q, sigma, band[det_i])
            power += scale2 * _mean0(_abs2(D)) / offsets.size
    # the error's odd and even lines differ by tens of dB (odd-symmetric error of a
    # half-wave symmetric signal): smooth each parity on its own
    local = np.empty_like(power)
    for parity in (0, 1):
        sel = band[det_i] % 2 == parity
        if sel.any():
            local[sel] = _running_mean(power[sel], 8)
    return np.maximum(power, 2.0 * local)


def _band_figures(odd_bins, odd_power, odd_noise, even_bins, even_power, even_noise,
                  det_bins, det_power, det_noise, fs, n, parity):
    """Per-octave figures of the non-excited lines: a band median hides a strong
    narrow-band nonlinearity, so each octave gets its median and its maximum excess over
    the noise, the count 6 dB over, and (parity grids) odd re even as a power ratio.
    Octaves start at the lowest detection line; the lowest ones are merged until a band
    holds 8 detection lines, a short last one joins the previous band."""
    if not det_bins.size:
        return []
    lo = float(det_bins[0])
    edges = [lo]
    while edges[-1] * 2 <= det_bins[-1]:
        edges.append(edges[-1] * 2)
    edges.append(float(det_bins[-1]) + 1)
    idx = np.searchsorted(edges, det_bins, side="right") - 1
    counts = np.bincount(idx, minlength=len(edges) - 1)
    # merge forward until a band holds 8 detection lines; a short last one joins the
    # previous band
    bounds, acc = [edges[0]], 0
    for i in range(len(edges) - 1):
        acc += counts[i]
        if acc >= 8:
            bounds.append(edges[i + 1])
            acc = 0
    if acc and len(bounds) > 1:
        bounds[-1] = edges[-1]
    elif acc or len(bounds) == 1:
        bounds.append(edges[-1])

    six_db = 10 * np.log10(4.0)

    def cls(bins, power, noise):
        """The figures of one class of lines in every band [bounds[i], bounds[i + 1])."""
        pos = np.searchsorted(bins, bounds)
        lo, hi = pos[:-1], pos[1:]
        n_lines = hi - lo
        full = n_lines > 0
        starts = np.minimum(lo, max(power.size - 1, 0))
        sums = np.add.reduceat(power, starts) if power.size else np.zeros(lo.size)
        if noise is not None and power.size:
            with np.errstate(divide="ignore", invalid="ignore"):
                ex = 10 * np.log10(power / noise)
            ex = np.where(np.isfinite(ex), ex, -np.inf)
            tops = np.maximum.reduceat(ex, starts)
            overs = np.add.reduceat((ex > six_db).astype(np.int64), starts)
        out = []
        for k in range(lo.size):
            entry = {"lines": int(n_lines[k]), "median_re_noise_db": None,
                     "max_re_noise_db": None, "lines_over_noise_6db": None, "power_db": None}
            out.append(entry)
            if not full[k]:
                continue
            mean = float(sums[k] / n_lines[k])
            entry["power_db"] = float(10 * np.log10(max(mean, 1e-300)))
            if noise is not None:
                med, top = float(_median(ex[lo[k]:hi[k]])), float(tops[k])
                entry.update({"median_re_noise_db": med if np.isfinite(med) else None,
                              "max_re_noise_db": top if np.isfinite(top) else None,
                              "lines_over_noise_6db": int(overs[k])})
        return out

    bands = [{"f_lo_hz": a * fs / n, "f_hi_hz": (b - 1) * fs / n}
             for a, b in zip(bounds[:-1], bounds[1:])]
    if parity:
        for entry, odd, even in zip(bands, cls(odd_bins, odd_power, odd_noise),
                                    cls(even_bins, even_power, even_noise)):
            entry["odd"], entry["even"] = odd, even
            po, pe = odd["power_db"], even["power_db"]
            entry["odd_re_even_db"] = None if po is None or pe is None else po - pe
    else:
        for entry, lines in zip(bands, cls(det_bins, det_power, det_noise)):
            entry["nonexcited"] = lines
    return bands


def _median_db_of(power):
    """_median(to_db(power)) from the middle value(s) only (10 log10 keeps the order;
    NaN when a value is NaN or <= 0, as to_db gives there)."""
    p = np.asarray(power, dtype=float).reshape(-1)
    if p.size == 0:
        return _median(p)
    if np.isnan(p).any() or (p <= 0).any():
        return np.float64(np.nan)
    k = (p.size - 1) // 2
    if p.size % 2:
        return to_db(np.partition(p, k)[k])
    part = np.partition(p, (k, k + 1))
    return (to_db(part[k]) + to_db(part[k + 1])) / 2.0


def _quantile_db_of(power, q):
    """np.quantile(to_db(power), q) (linear interpolation) from the two neighbouring
    order statistics only; power > 0 and finite (else np.quantile itself)."""
    p = np.asarray(power, dtype=float).reshape(-1)
    if p.size == 0 or not np.isfinite(p).all() or (p <= 0).any():
        return np.quantile(to_db(p), q)
    pos = q * (p.size - 1)
    lo = int(np.floor(pos))
    hi = min(lo + 1, p.size - 1)
    part = np.partition(p, (lo, hi) if hi != lo else lo)
    a, b = float(to_db(part[lo])), float(to_db(part[hi]))
    t = pos - lo
    # numpy's lerp: a + t (b - a), from the upper end when t >= 0.5
    return b - (b - a) * (1.0 - t) if t >= 0.5 else a + (b - a) * t


def _median_db(values_db):
    """Median of per-line dB values; NaN (no variance there) counts as -inf. None when
    more than half are -inf or there is no value."""
    v = np.asarray(values_db, dtype=float)
    if v.size == 0:
        return None
    med = float(_median(np.where(np.isnan(v), -np.inf, v)))
    return med if np.isfinite(med) else None


def robust_bla(u, y, r=None, *, fs=1.0, settle_periods=0, excited_bins=None,
               warn_transient=True, y_quantisation_step=None):
    """Robust BLA with total, noise and nonlinear variances, and nonlinear detection.

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
        Excited DFT bins (the design grid when known); found from the spectrum of r (or
        u) by default (:func:`detect_excited_lines`).
    warn_transient : bool
        Emit a :class:`TransientWarning` when the transient check is suspect.
    y_quantisation_step : float, optional
        Quantisation step of the measured output (unit of y, e.g. 2 pi / counts per
        revolution in rad): its floor q^2/12 spread over the band is compared with the
        plant-referred distortion.

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
    fs, settle = check_arguments(fs=fs, n_period=n, settle_periods=settle_periods,
                                 n_total=n_total)
    # the layout and the steady state of the excitation, before anything is averaged
    layout = check_blocks(r if r is not None else u, kind="multisine", settle_periods=settle,
                          name="reference r" if r is not None else "input u", fs=fs,
                          mixed_levels="note", want_mean_spectrum=excited_bins is None)
    if layout.changed:
        u, y = layout.apply(u), layout.apply(y)
        r = None if r is None else layout.apply(r)
        n_real, n_total, n = u.shape
        settle = layout.settle_periods
    excitation = r if r is not None else u
    detected_here = excited_bins is None
    line_note = None
    strays = None
    if detected_here:
        # the spectrum of the period sums: the checks' (of the period means) reused
        sums = (None if layout.mean_spectrum is None or excitation.dtype != np.float64 else
                layout.mean_spectrum * (n_total - settle))
        try:
            excited, info = detect_excited_lines(excitation, settle, return_info=True,
                                                 _spectrum=sums)
        except InputError as exc:
            if "NaN" in str(exc):
                _locate_bad((("reference r" if r is not None else "input u", excitation),), fs)
            raise
        line_note = info["note"]
        strays = info.get("stray_bins")
    else:
        excited = _validate_lines(excited_bins, n)
    band = np.arange(excited[0], excited[-1] + 1)
    # resolution of the recorded numbers: float32 records round to 2^-24 of the value
    # (a sample of every 97th value is enough to tell float32 records; the input's largest
    # magnitude is bounded by twice the sample's, the output's is taken exactly). Read per
    # realization just before its FFT (its samples are then in cache, no extra pass).
    per_real = n_total * n
    extremes = {"u": [0.0, True], "y": [0.0, True]}     # largest |value|, float32-exact

    def scan(x, m, acc, exact):
        flat = x[m].reshape(-1)
        sample = flat[(-m * per_real) % 97::97]       # its part of x.reshape(-1)[::97]
        if acc[1] and x.dtype != np.float32:
            acc[1] = np.array_equal(sample, sample.astype(np.float32))
        top = (max(float(flat.max()), -float(flat.min())) if exact else
               2.0 * float(np.max(np.abs(sample))) if sample.size else 0.0)
        if np.isfinite(top):
            acc[0] = max(acc[0], top)
        else:
            acc.append(m)           # NaN or inf (in a dropped settle period, or an error)

    def rounding(name):
        top, f32 = extremes[name][:2]
        if len(extremes[name]) > 2:
            # a non-finite value: the largest finite one (a NaN or inf in a settle period
            # must not make every noise level NaN; one in a kept period is refused later)
            values = y if name == "y" else u.reshape(-1)[::97]
            values = values[np.isfinite(values)]
            top = 0.0 if not values.size else \
                float(np.max(np.abs(values))) * (1.0 if name == "y" else 2.0)
        return top * (2.0 ** -24 if f32 else 2.0 ** -53)

    lo, hi = int(band[0]), int(band[-1]) + 1      # the band is contiguous: a view, no copy

    # float64 records: each realization's spectra go into the same buffers (rfft's out=:
    # no allocation per call, the buffers stay in cache); robust_bla_spectra may
    # overwrite them (it takes the deviations from the period mean in place)
    # (one buffer per signal, even when r is u: each is overwritten separately)
    signals = (u, y, r)
    buffers = [np.empty((n_total, n // 2 + 1), np.complex128)
               if x is not None and x.dtype == np.float64 else None for x in signals]

    dc_y = np.empty((n_real, n_total))     # the output's DC per period (drift check)
    dc_u = np.empty((n_real, n_total))     # the input's (a drift of the input is named)
    # detection lines above the band (every grid; a full grid has none inside it): up to
    # 3 times the highest excited line, inside fs/2; their moments are read from the same
    # spectra (one slice per realization). With a reference, the measured input's too
    # (what its own content there explains through the plant is accounted for)
    a_lo, a_hi = hi, min(3 * int(excited[-1]), (n + 1) // 2 - 1) + 1
    above = None
    above_keys = ("y", "x", "u") if r is not None else ("y", "x")
    if a_hi > a_lo and n_total - settle >= 2:
        above = {key: (np.empty((n_real, a_hi - a_lo), np.complex128),
                       np.empty((n_real, a_hi - a_lo))) for key in above_keys}

    def one_realization(m):
        scan(u, m, extremes["u"], False)
        scan(y, m, extremes["y"], True)
        if buffers[1] is None:
            dc_y[m] = np.add.reduce(y[m], axis=-1, dtype=np.float64)
        out = []
        full = {}
        for x, buf in zip(signals, buffers):
            if x is None:
                out.append(None)
            elif buf is not None and x is r and n_total - settle > 1 \
                    and (r[m, settle + 1:] == r[m, settle]).all():
                # a reference that repeats exactly (the designed signal): the spectra of
                # its kept periods are the same, one FFT (the periods before are not read)
                np.fft.rfft(r[m, settle:settle + 1], axis=-1, out=buf[settle:settle + 1])
                buf[settle + 1:] = buf[settle]
                out.append(buf[:, lo:hi])
                full[id(x)] = buf
            elif buf is not None:
                out.append(np.fft.rfft(x[m], axis=-1, out=buf)[:, lo:hi])
                full[id(x)] = buf
            else:
                spec = np.fft.rfft(x[m], axis=-1)
                full[id(x)] = spec
                out.append(spec[:, lo:hi].astype(np.complex128))
        if buffers[1] is not None:
            dc_y[m] = buffers[1][:, 0].real
        dc_u[m] = (np.add.reduce(u[m], axis=-1, dtype=np.float64) if buffers[0] is None
                   else buffers[0][:, 0].real)
        if above is not None:
            for key, x in zip(above_keys, (y, r if r is not None else u, u)):
                part = np.array(full[id(x)][settle:, a_lo:a_hi], dtype=np.complex128)
                above[key][0][m], above[key][1][m] = _spread2_inplace(part)
        return tuple(out)

    y_mean_time = None
    if y_quantisation_step:
        y_mean_time = np.add.reduce(y[:, settle:, :], axis=1, dtype=np.float64) / (n_total - settle)
    lpm_note = []

    def before_estimate(transient, y_rnd, u_rnd):
        """After the periods are read: a transient in the kept periods, or a drift of the
        output, takes the local polynomial method (its result replaces the plain one)."""
        drift = _drift_test(dc_y[:, settle:])
        if n_total - settle < 2 or not (transient.suspect or drift is not None):
            return None
        out, note = _lpm_result(transient, drift, u, y, r, band=band, excited=excited,
                                settle=settle, fs=fs, n=n,
                                y_quantisation_step=y_quantisation_step, y_rounding=y_rnd,
                                u_rounding=u_rnd, y_mean_time=y_mean_time, strays=strays)
        if note:
            lpm_note.append(note)
        return out

    try:
        res = robust_bla_spectra(None, None, bins=band, n_period=n, fs=fs, settle_periods=settle,
                                 excited_bins=excited, warn_transient=False,
                                 y_quantisation_step=y_quantisation_step,
                                 y_rounding=lambda: rounding("y"), _get=one_realization, _shape=(n_real, n_total),
                                 _known_ref=r is not None, _y_mean_time=y_mean_time,
                                 _ignore_bins=strays, _u_rounding=lambda: rounding("u"),
                                 _before=before_estimate)
    except InputError as exc:
        if "non-finite" in str(exc) or "zero power" in str(exc):
            _locate_bad((("input u", u), ("output y", y), ("reference r", r)), fs)
        raise
    if detected_here:
        margin = info.get("margin_db")
        res.notes.insert(0, f"excited lines found from the spectrum of "
                            f"{'r' if r is not None else 'u'}: {excited.size} lines "
                            f"{excited[0] * fs / n:g} .. {excited[-1] * fs / n:g} Hz"
                            + ("" if margin is None else
                               f", {info['confidence']} ({margin:.0f} dB between the weakest "
                               f"excited and the strongest other line of the band)"))
        res.summary["excited_lines_margin_db"] = margin
        res.summary["excited_lines_confidence"] = info["confidence"]
    if line_note:
        res.notes.insert(1, line_note)
    res.notes.extend(layout.notes)
    if above is not None:
        _above_band(res, above, a_lo, n, n_total - settle, rounding("y"),
                    "reference r" if r is not None else "input u",
                    float(np.mean(np.square(layout.levels))) if layout.levels is not None
                    else float(np.nanmean(np.square(excitation[:, settle:]))))
    if lpm_note:
        res.notes.append(lpm_note[0])
    drift_u = _drift_test(dc_u[:, settle:])
    rms_u = float(np.sqrt(np.mean(np.square(layout.levels)))) \
        if layout.levels is not None and r is None else float(np.sqrt(np.mean(np.square(
            u[:, settle:].reshape(-1)[::97])))) if drift_u is not None else 0.0
    # (a drift under 0.1 % of the input's rms over the kept periods is not said)
    if drift_u is not None and \
            abs(drift_u[1] / n) * (n_total - settle) > 1e-3 * rms_u:
        m_d, slope, t_d = drift_u
        res.summary["input_drift_per_period"] = slope / n
        res.notes.append(
            f"input u drifts: its mean moves {slope / n:+.3g} per period in realization {m_d} "
            f"(t = {t_d:+.3g}; {100 * abs(slope / n) * (n_total - settle) / rms_u:.2g} % of "
            f"its rms over the kept periods): a slow drift of the input (an offset that "
            f"moves, a sensor warming up), not periodic; its leakage lies at every line of "
            f"u" + ("; the 'distorted' figures of u above count it" if res.summary.get(
                "excitation_distorted") and r is None else "")
            + "; G at the excited lines holds when the plant received the same input")
    if res.transient.suspect and warn_transient:
        warnings.warn(res.transient.message, TransientWarning, stacklevel=2)
    return res


def _above_band(res, above, a_lo, n, n_per, y_rounding, xname, x_power):
    """Detection lines above the band (every grid): the lines up to 3 times the highest
    excited one (inside fs/2) where the excitation is clean (its period mean not 6 dB
    over its noise, or 100 dB under its power ``x_power``: where the excitation itself
    has content, G there would be needed to tell it from plant distortion). With a
    reference r, the measured input u can still have content at those lines (the loop
    feeds the output back): what it explains through the plant is added to what is
    expected there, bounded by the largest |G| of the highest tenth of the excited
    lines (a plant that falls off above the band; the plant-referred levels in the
    band subtract the interpolated G U likewise). The output's level there against its
    noise, by the class test of the non-excited lines; the ``above_band_*`` keys and a
    note. A full grid's verdict comes from them; on other grids they are detection
    lines beside those in the band (:func:`level_verdict`)."""
    scale2 = (2.0 / n) ** 2
    n_real = above["y"][0].shape[0]
    k = n_per * (n_per - 1)
    y_level = scale2 * _mean0(_abs2(above["y"][0]))
    floor = 4.0 * (2.0 * float(y_rounding)) ** 2 / 12.0 / n
    y_noise = scale2 * _mean0(above["y"][1]) / k + floor
    x_level = scale2 * _mean0(_abs2(above["x"][0]))
    x_noise = scale2 * _mean0(above["x"][1]) / k
    clean = (x_level <= 4.0 * x_noise) | (x_level <= 1e-10 * x_power)
    explained = np.zeros(clean.shape, dtype=bool)
    if "u" in above:
        # the measured input's own content where it stands over its noise, through the
        # plant (|G| extrapolated from the highest tenth of the excited lines by a power
        # law that does not rise): where it reaches a quarter of the output's noise the
        # line cannot be told from distortion without G there, and is left out
        u_level = scale2 * _mean0(_abs2(above["u"][0]))
        u_noise = scale2 * _mean0(above["u"][1]) / k
        g_ext2 = _g_extrapolated2(res.freq, res.G, (a_lo + np.arange(clean.size)) * res.fs / n)
        explained = clean & (u_level > 4.0 * u_noise) & (g_ext2 * u_level > 0.25 * y_noise)
        clean = clean & ~explained
    # output lines 100 dB or more under its strongest excited line: rounding, not distortion
    top = float(np.nanmax(10 ** (np.asarray(res.output_db, dtype=float) / 10)))
    y_level = np.where(y_level <= 1e-10 * top, 0.0, y_level)
    bins = np.arange(a_lo, a_lo + y_level.size)[clean]
    # (fewer than 8 clean lines: too few to say anything, no figures)
    st = _class_stats(y_level[clean], y_noise[clean] if bins.size >= 8 else None,
                      n_real * (n_per - 1), "above_band_")
    res.summary.update(st)
    res.summary["above_band_hz"] = (None if not bins.size else
                                    [float(bins[0] * res.fs / n), float(bins[-1] * res.fs / n)])
    res.summary["above_band_lines_excitation_not_clean"] = int(np.sum(~clean & ~explained))
    res.summary["above_band_lines_input_content"] = int(np.sum(explained))
    if st["above_band_detected"] is None:
        return
    res.notes.append(
        f"above the band: {bins.size} line(s) {bins[0] * res.fs / n:g} .. "
        f"{bins[-1] * res.fs / n:g} Hz where the {xname} is clean (at its noise; "
        f"{int(np.sum(~clean))} others left out"
        + (f", {int(np.sum(explained))} of them for the measured input's own content"
           if explained.any() else "") + "), output "
        + (f"{st['above_band_line_median_re_noise_db']:+.1f} dB re its noise (median), "
           if st["above_band_line_median_re_noise_db"] is not None else "")
        + f"{st['above_band_lines_over_noise_6db']} of {bins.size} lines 6 dB over "
        f"({st['above_band_lines_needed']} needed): "
        + ("nonlinear distortion above the band" if st["above_band_detected"] else
           "no distortion above the band"))


def _g_extrapolated2(freq, G, f_at):
    """|G|^2 at ``f_at`` above the band: a power law in the frequency fitted (least
    squares in log-log) to the highest tenth (at least 3) of the excited lines, its
    slope capped at 0 (a plant does not rise above its band here)."""
    g = np.abs(np.asarray(G))
    f = np.asarray(freq, dtype=float)
    top = max(3, g.size // 10)
    lf, lg = np.log(f[-top:]), np.log(np.maximum(g[-top:], 1e-300))
    if g.size >= 2:
        slope = float(np.polyfit(lf, lg, 1)[0]) if np.ptp(lf) > 0 else 0.0
    else:
        slope = 0.0
    slope = min(slope, 0.0)
    at_top = float(np.mean(lg) + slope * (np.log(f[-1]) - np.mean(lf)))
    return np.exp(2.0 * (at_top + slope * (np.log(np.asarray(f_at)) - np.log(f[-1]))))


def _drift_test(dc, t_limit=6.0):
    """A trend in the output's DC over the kept periods (``dc`` (M, P): the DC line of each
    period): the least-squares slope per realization against its standard error from the
    residuals. Returns (realization, slope per period re the DC's scatter, t) of the most
    significant one when |t| > t_limit (P >= 4), else None."""
    m_real, p = dc.shape
    if p < 4 or not np.all(np.isfinite(dc)):
        return None
    t = np.arange(p) - (p - 1) / 2.0
    stt = float(np.sum(t * t))
    slope = (dc - dc.mean(axis=1, keepdims=True)) @ t / stt
    resid = dc - dc.mean(axis=1, keepdims=True) - slope[:, None] * t
    s2 = np.sum(resid ** 2, axis=1) / (p - 2)
    scale = np.maximum(np.sqrt(s2), 1e-12 * np.maximum(np.abs(dc).max(axis=1), 1e-300))
    tstat = slope * np.sqrt(stt) / scale
    m = int(np.argmax(np.abs(tstat)))
    if abs(tstat[m]) <= t_limit:
        return None
    return m, float(slope[m]), float(tstat[m])


def _lpm_result(transient, drift, u, y, r, *, band, excited, settle, fs, n,
                y_quantisation_step, y_rounding, u_rounding, y_mean_time, strays):
    """The robust BLA from the local polynomial method's line moments, when the periods
    show a transient (always) or the output drifts (when the LPM finds the drift at the
    excited lines above its noise). Returns (result or None, note): None keeps plain
    averaging (the note says why)."""
    from fftune.analysis.lpm import lpm_moments
    mom, G_per, info = lpm_moments(u, y, r, band=band, excited=excited, settle_periods=settle)
    what = "transient" if transient.suspect else "drift"
    size = (f"{info.transient_re_output_db:.1f} dB re the output at the excited lines, "
            f"median {info.transient_re_noise_db:+.1f} dB re its standard error, "
            f"{info.lines_significant} of {G_per[0].size} line(s) 6 dB over it")
    drift_text = "" if drift is None else \
        (f" (the output's DC moves {drift[1]:+.3g} per period in realization {drift[0]}, "
         f"t = {drift[2]:+.1f})")
    if not transient.suspect and not info.significant:
        return None, (f"the output drifts{drift_text}, but the local polynomial method finds "
                      f"it under the noise at the excited lines ({size}): plain averaging "
                      f"kept")
    if transient.suspect:
        transient.message += " (removed here by the local polynomial method)"
    out = _bla_from_moments(mom, excited=excited, n=n, fs=fs, settle=settle, Y_exc=None,
                            G_per=None if r is not None else G_per, warn_transient=False,
                            y_quantisation_step=y_quantisation_step, y_rounding=y_rounding,
                            y_mean_time=y_mean_time, ignore_bins=strays, u_rounding=u_rounding,
                            transient=transient)
    out.notes.append(
        f"{what}{drift_text} removed by the local polynomial method (degree {info.order} over "
        f"{info.neighbours} neighbouring bins of the whole record, {info.dof} degrees of "
        f"freedom per line): its size {size}; the BLA and its noise variance are from all "
        f"{mom.n_periods} periods")
    out.summary["lpm"] = {"removed": what, "transient_re_output_db": info.transient_re_output_db,
                          "transient_re_noise_db": info.transient_re_noise_db,
                          "lines_significant": info.lines_significant,
                          "order": info.order, "neighbours": info.neighbours, "dof": info.dof}
    return out, None


@dataclass
class LineMoments:
    """Sufficient statistics of a periodic experiment at a set of DFT lines: per
    realization, the means over the P kept periods of the per-period spectra and the
    sums of squared deviations (what the robust BLA with known reference reads; a drive
    can accumulate them while it runs, :mod:`fftune.analysis.stats`).

    Attributes
    ----------
    bins : ndarray of int, shape (L,)
        DFT bins, ascending.
    n_periods : int
        P, the periods each mean is taken over.
    U, Y : ndarray of complex, shape (M, L)
        mean_p X_p of the input and output spectra (numpy ``rfft`` scaling, no 1/N).
    ss_u, ss_y : ndarray, shape (M, L)
        sum_p |X_p - mean|^2.
    s_yu : ndarray of complex, shape (M, L)
        sum_p (Y_p - mean Y) conj(U_p - mean U).
    R : ndarray of complex, shape (M, L), or None
        mean_p R_p of the reference (None: no reference).
    ss_r : ndarray, shape (M, L), or None
        sum_p |R_p - mean|^2 (None: the reference is taken as exactly periodic, 0).
    """

    bins: np.ndarray
    n_periods: int
    U: np.ndarray
    Y: np.ndarray
    ss_u: np.ndarray
    ss_y: np.ndarray
    s_yu: np.ndarray
    R: np.ndarray = None
    ss_r: np.ndarray = None


def robust_bla_spectra(U, Y, R=None, *, bins, n_period, fs=1.0, settle_periods=0,
                       excited_bins, warn_transient=True, y_quantisation_step=None,
                       y_rounding=0.0, _get=None, _shape=None, _known_ref=False,
                       _y_mean_time=None, _ignore_bins=None, _u_rounding=0.0, _before=None):
    """The robust BLA of :func:`robust_bla` from per-period spectra.

    Parameters
    ----------
    U, Y : array_like of complex, shape (M, T + P, L)
        DFT of every period of input and output (numpy ``rfft`` scaling, no 1/N) at the
        DFT bins ``bins``.
    R : array_like of complex, shape (M, T + P, L), optional
        The same for the reference (known-reference estimate).
    bins : array_like of int, shape (L,)
        Bin of each column, ascending; must hold every bin from the lowest to the
        highest excited one (the detection lines).
    n_period : int
        Samples per period N (levels are |DFT| 2 / N).
    fs, settle_periods, warn_transient, y_quantisation_step
        As in :func:`robust_bla`.
    excited_bins : array_like of int
        Excited bins (a subset of ``bins``).
    y_rounding : float
        Largest rounding error of the recorded output values (e.g. 2^-24 max|y| for
        float32 records): its floor (uniform, spread over the band) is added to the
        noise at the non-excited lines, so that the rounding of a periodic record (the
        same in every period, hence not in the noise estimate) is not taken for
        distortion. (:func:`robust_bla` passes a function, called once every
        realization has been read.)

    Returns
    -------
    BLAResult
    """
    n = int(n_period)
    bins = np.asarray(bins, dtype=np.int64).reshape(-1)
    if _get is None:     # public use: whole arrays; robust_bla passes one realization at a time
        # complex128 (real spectra too: the sums of squares view them as re, im pairs)
        U, Y = np.asarray(U, dtype=np.complex128), np.asarray(Y, dtype=np.complex128)
        R = None if R is None else np.asarray(R, dtype=np.complex128)
        for name, arr in (("U", U), ("Y", Y), ("R", R)):
            if arr is not None and (arr.ndim != 3 or arr.shape[2] != bins.size
                                    or arr.shape != U.shape):
                raise InputError(f"spectra {name}: expected shape (M, T+P, {bins.size}) like "
                                 f"U {U.shape}, got {arr.shape}")
        _shape = U.shape[:2]
    n_real, n_total = _shape
    fs, settle = check_arguments(fs=fs, n_period=n, settle_periods=settle_periods,
                                 n_total=n_total, hold_text=False)
    excited = _validate_lines(excited_bins, n)
    n_per = n_total - settle
    band = np.arange(excited[0], excited[-1] + 1)
    pos = _band_positions(bins, band)
    is_exc = _in_band(band, excited)
    known_ref = R is not None if _get is None else _known_ref
    if _get is None:
        def _get(m):
            return U[m][:, pos], Y[m][:, pos], None if R is None else R[m][:, pos]
    # Per realization (its (T+P, lines) spectra stay in cache): reductions over the
    # periods only, (M, lines)-sized results: the line moments, plus the excited lines
    # of every period for the transient check (and the per-period ratio without a
    # reference).
    exc_i = np.flatnonzero(is_exc)
    c = np.complex128
    L = band.size
    # the transient check reads at most 256 lines spread over the band: keep only those
    trans_i = exc_i if exc_i.size <= 256 else \
        exc_i[np.linspace(0, exc_i.size - 1, 256).astype(np.int64)]
    Y_exc = np.empty((n_real, n_total, trans_i.size), c)
    mU, mY, mR = np.empty((n_real, L), c), np.empty((n_real, L), c), np.empty((n_real, L), c)
    ss_u, ss_y, ss_r = np.empty((n_real, L)), np.empty((n_real, L)), np.empty((n_real, L))
    s_yu = np.empty((n_real, L), c)
    G_per = None if known_ref else (np.empty((n_real, exc_i.size), c), np.empty((n_real, exc_i.size)))
    # work buffers, allocated once (fresh large temporaries in every realization cost
    # page faults comparable to the arithmetic)
    prod = np.empty((n_per, L), c)
    if not known_ref:
        Ue, Ge = np.empty((n_per, exc_i.size), c), np.empty((n_per, exc_i.size), c)
    for m in range(n_real):
        Um, Ym, Rm = _get(m)        # (T + P, L) complex128, overwritten below
        Y_exc[m] = Ym[:, trans_i]
        if Rm is None:
            # per-period ratio at the excited lines (mode="clip": valid indices, no
            # intermediate buffer)
            np.take(Um[settle:], exc_i, axis=1, out=Ue, mode="clip")
            np.take(Ym[settle:], exc_i, axis=1, out=Ge, mode="clip")
            with np.errstate(divide="ignore", invalid="ignore"):
                np.divide(Ge, Ue, out=Ge)
            G_per[0][m], G_per[1][m] = _spread2_inplace(Ge)
        else:
            mR[m], ss_r[m] = _spread2_inplace(Rm[settle:])
        dU, dY = Um[settle:], Ym[settle:]
        mU[m], ss_u[m] = _spread2_inplace(dU)        # dU, dY: now the deviations
        mY[m], ss_y[m] = _spread2_inplace(dY)
        np.conjugate(dU, out=prod)
        prod *= dY
        s_yu[m] = np.add.reduce(prod, axis=0)
    mom = LineMoments(bins=band, n_periods=n_per, U=mU, Y=mY, ss_u=ss_u, ss_y=ss_y, s_yu=s_yu,
                      R=mR if known_ref else None, ss_r=ss_r if known_ref else None)
    if callable(y_rounding):        # (robust_bla: known once every realization is read)
        y_rounding, _u_rounding = y_rounding(), _u_rounding()
    transient = None
    if _before is not None:
        # (robust_bla: the transient and the drift decide between this estimate and the
        # local polynomial method's, before this one is computed)
        transient = _transient(Y_exc, settle, n_per)
        early = _before(transient, y_rounding, _u_rounding)
        if early is not None:
            return early
    return _bla_from_moments(mom, excited=excited, n=n, fs=fs, settle=settle, Y_exc=Y_exc,
                             G_per=G_per, warn_transient=warn_transient,
                             y_quantisation_step=y_quantisation_step, y_rounding=y_rounding,
                             y_mean_time=_y_mean_time, ignore_bins=_ignore_bins,
                             u_rounding=_u_rounding, transient=transient)


def _band_positions(bins, band):
    """Columns of ``bins`` that hold the lines ``band`` (every one must be there)."""
    pos = np.searchsorted(bins, band)
    if np.any(pos >= bins.size) or np.any(bins[np.minimum(pos, bins.size - 1)] != band):
        raise InputError(f"spectra: bins must hold every line {band[0]} .. {band[-1]} "
                         f"between the lowest and the highest excited line")
    return pos


def robust_bla_moments(moments, *, n_period, fs=1.0, excited_bins, y_quantisation_step=None,
                       y_rounding=0.0):
    """The robust BLA with known reference from line moments (:class:`LineMoments`), e.g.
    a drive's line statistics: the same estimate as :func:`robust_bla` of the samples.

    Parameters
    ----------
    moments : LineMoments
        With the reference ``R`` (the moments hold no per-period ratio, so only the
        known-reference estimate is possible); its bins must hold every line from the
        lowest to the highest excited one.
    n_period : int
        Samples per period N.
    fs : float
        Sample rate (Hz).
    excited_bins : array_like of int
        Excited bins (the design grid).
    y_quantisation_step, y_rounding
        As in :func:`robust_bla_spectra`.

    Returns
    -------
    BLAResult
        Its ``transient`` is not checked (the moments keep no single period): the note
        says so.
    """
    n = int(n_period)
    fs, _ = check_arguments(fs=fs, n_period=n)
    if moments.R is None:
        raise InputError("line moments: the reference R is needed (known-reference estimate)")
    excited = _validate_lines(excited_bins, n)
    bins = np.asarray(moments.bins, dtype=np.int64).reshape(-1)
    band = np.arange(excited[0], excited[-1] + 1)
    pos = _band_positions(bins, band)
    fields = ("U", "Y", "ss_u", "ss_y", "s_yu", "R", "ss_r")
    arrays = {}
    for name in fields:
        value = getattr(moments, name)
        if value is None:
            arrays[name] = None
            continue
        value = np.asarray(value)
        if value.ndim != 2 or value.shape[1] != bins.size or value.shape[0] != np.shape(moments.U)[0]:
            raise InputError(f"line moments {name}: expected shape (M, {bins.size}) like U "
                             f"{np.shape(moments.U)}, got {value.shape}")
        arrays[name] = value[:, pos]
    if int(moments.n_periods) < 1:
        raise InputError(f"line moments: P = {moments.n_periods} periods, need at least 1")
    mom = LineMoments(bins=band, n_periods=int(moments.n_periods), **arrays)
    return _bla_from_moments(mom, excited=excited, n=n, fs=fs, settle=0, Y_exc=None, G_per=None,
                             warn_transient=False, y_quantisation_step=y_quantisation_step,
                             y_rounding=y_rounding)


def _bla_from_moments(mom, *, excited, n, fs, settle, Y_exc, G_per, warn_transient,
                      y_quantisation_step, y_rounding, y_mean_time=None, ignore_bins=None,
                      u_rounding=0.0, transient=None):
    """The estimate and the detection from the line moments over the band (bins from the
    lowest to the highest excited line). ``Y_exc`` (M, T + P, E): every period's output
    at the excited lines for the transient check (None: not checked). ``G_per``: per
    realization the mean and sum of squared deviations over periods of Y / U at the
    excited lines (the estimate without a reference; None with one). ``y_mean_time``
    (M, N): the period-averaged output in time (for the quantisation model; None: the
    white floor q^2/12 only). ``ignore_bins``: lines that are neither excited nor usable
    for detection (stray input tones found by the line finder)."""
    band = mom.bins
    n_real, n_per = mom.U.shape[0], mom.n_periods
    is_exc = _in_band(band, excited)
    is_det = ~is_exc
    if ignore_bins is not None and np.size(ignore_bins):
        is_det &= ~np.isin(band, ignore_bins)
    det_bins = band[is_det]
    gridinfo = classify_grid(excited, n)
    if gridinfo["parity"]:
        odd_sel, even_sel = det_bins % 2 == 1, det_bins % 2 == 0
    else:
        odd_sel = even_sel = np.zeros(det_bins.size, dtype=bool)
    odd_bins, even_bins = det_bins[odd_sel], det_bins[even_sel]
    scale2 = (2.0 / n) ** 2        # |DFT|^2 -> squared amplitude of the line (levels only)
    freq = excited * fs / n

    def check_finite(*values):
        if not all(np.isfinite(v).all() for v in values if v is not None):
            raise InputError("non-finite result (overflow in the input data?)")

    def check_power(name, power):
        # "zero" power: 120 dB or more under the median excited line (rounding noise)
        check_finite(power)
        low = np.flatnonzero(~(power > 1e-12 * _median(power)))
        if low.size:
            raise InputError(
                f"{name}: zero power at {low.size} excited line(s) "
                f"{', '.join(f'{excited[i] * fs / n:g} Hz' for i in low[:5])}"
                f"{' ...' if low.size > 5 else ''} (wrong excited lines?)")

    known_ref = G_per is None
    exc_i, det_i = np.flatnonzero(is_exc), np.flatnonzero(is_det)
    U_mean_e, Y_mean_e = mom.U[:, exc_i], mom.Y[:, exc_i]
    # sum over realizations and periods of |U_p|^2 = P |mean|^2 + sum |deviation|^2
    ue_abs2 = _abs2(U_mean_e)
    u_power = np.sum(n_per * ue_abs2 + mom.ss_u[:, exc_i], axis=0)
    ud, yd = mom.U[:, det_i], mom.Y[:, det_i]
    ud_ss, yd_ss, yud = mom.ss_u[:, det_i], mom.ss_y[:, det_i], mom.s_yu[:, det_i]
    if known_ref:
        R_mean = xe = mom.R[:, exc_i]
        xd = mom.R[:, det_i]
        xd_ss = np.zeros(xd.shape) if mom.ss_r is None else mom.ss_r[:, det_i]
    else:
        xd, xd_ss, xe = ud, ud_ss, U_mean_e
    check_power("input u", u_power)
    notes = []
    if not known_ref:
        G_m, G_ss = G_per
        check_finite(G_m)
        G = G_m.mean(axis=0)
        var_total = var_noise = None
        if n_real >= 2:
            var_total = _abs2_sum((G_m - G)[:, None, :], axis=0)[0] / (n_real * (n_real - 1))
        if n_per >= 2:
            var_noise = G_ss.sum(axis=0) / (n_per * (n_per - 1)) / n_real ** 2
        u_level = _mean0(ue_abs2)
        x_exc_abs2 = u_level                # the excitation's own level (known input)
    else:
        check_power("reference r", np.sum(_abs2(R_mean), axis=0))
        # rotate each realization by conj(R / |R|) (removes its random phase); the sums
        # of squared deviations and the cross sum do not change under the rotation
        with np.errstate(divide="ignore", invalid="ignore"):
            rot = np.conj(R_mean / np.abs(R_mean))
        U_m, Y_m = U_mean_e * rot, Y_mean_e * rot
        su2, sy2, syu = mom.ss_u[:, exc_i], mom.ss_y[:, exc_i], mom.s_yu[:, exc_i]
        U_bar, Y_bar = U_m.mean(axis=0), Y_m.mean(axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            G = Y_bar / U_bar
        check_finite(G)
        u_level = _abs2(U_bar)
        x_exc_abs2 = None

        def propagate(s2y, s2u, cyu):
            return (s2y + _abs2(G) * s2u - 2 * np.real(np.conj(G) * cyu)) / u_level

        var_total = var_noise = None
        if n_real >= 2:
            du, dy = U_m - U_bar, Y_m - Y_bar
            k = n_real * (n_real - 1)
            var_total = propagate(np.sum(_abs2(dy), 0) / k, np.sum(_abs2(du), 0) / k,
                                  np.sum(dy * np.conj(du), 0) / k)
        if n_per >= 2:
            k = n_per * (n_per - 1) * n_real ** 2
            var_noise = propagate(sy2.sum(0) / k, su2.sum(0) / k, syu.sum(0) / k)

    var_nl = var_nl_negative = None
    # the excited lines' own test: without nonlinear distortion var_total / var_noise is
    # F(2 (M - 1), 2 M (P - 1)) distributed (both estimate the noise variance of G)
    d1, d2 = 2 * (n_real - 1), 2 * n_real * (n_per - 1)
    excited_stats = _class_stats(np.zeros(excited.size), None, 0, "excited_")
    neg_fraction_expected = None
    if var_total is not None and var_noise is not None:
        var_nl = n_real * (var_total - var_noise)
        var_nl_negative = var_nl < 0
        # the rounding of the recorded numbers is the same in every period (not in
        # var_noise) but differs between realizations (in var_total): its variance of G
        # (uniform error of +-rounding per sample: N rounding^2 / 3 per line) is added
        round_var = (n * (float(y_rounding) ** 2 + _abs2(G) * float(u_rounding) ** 2)
                     / 3.0 / np.maximum(u_level, 1e-300) / n_real)
        ref_var = var_noise + round_var
        with np.errstate(divide="ignore", invalid="ignore"):
            excited_stats = _class_stats(var_total, np.where(ref_var > 0, ref_var, np.nan),
                                         d2 / 2, "excited_",
                                         tail=lambda x: f_sf_even(x, d1, d2))
        neg_fraction_expected = float(1.0 - f_sf_even(np.array(1.0), d1, d2))
        n_neg = int(var_nl_negative.sum())
        if n_neg:
            notes.append(f"var_nl < 0 at {n_neg} of {excited.size} lines "
                         f"(noise estimate above the total: no detectable nonlinear "
                         f"variance there)")
            # noise alone puts var_total under var_noise at a fraction P(F < 1) of the
            # lines; many more mean the period-to-period spread exceeds the spread over
            # realizations: not noise, not distortion
            sf = _binom_sf_counts(excited.size, neg_fraction_expected)
            if sf[n_neg] <= 1e-3:
                notes.append(
                    f"{100 * n_neg / excited.size:.0f} % of the lines have var_nl < 0 where "
                    f"noise alone gives {100 * neg_fraction_expected:.0f} %: the periods differ "
                    f"more than the realizations do, so the noise variance is overestimated: "
                    f"a disturbance periodic in 2N or longer (not synchronous with the period), "
                    f"drift or non-stationary noise; the nonlinear variance is then "
                    f"underestimated (check the record for a slow disturbance, use fewer periods "
                    f"or more realizations)")
    if n_real < 2:
        notes.append("M = 1 realization: no total or nonlinear variance (needs M >= 2)")
    if n_per < 2:
        notes.append("P = 1 period: no noise variance (needs P >= 2)")
    if not det_bins.size and excited_stats["excited_detected"] is not None:
        notes.append("no non-excited line: nonlinear distortion judged at the excited lines "
                     "(var_total vs var_noise per line, F test, Bonferroni over the lines); no "
                     "odd/even and no plant-referred claim possible")
    if not gridinfo["parity"]:
        notes.append(gridinfo["note"])

    # Figure 3 view (levels as squared line amplitudes, scale2)
    output_power = scale2 * _mean0(_abs2(Y_mean_e))
    u_level = scale2 * u_level
    nl_power = None if var_nl is None else var_nl * u_level
    noise_power = None if var_noise is None else n_real * var_noise * u_level

    rounding_floor = 4.0 * (2.0 * float(y_rounding)) ** 2 / 12.0 / n

    def line_levels(mean, ss, floor=0.0, mean_abs2=None):
        """Level (mean over m of |period mean|^2) and noise of the period mean (plus a
        rounding floor) from the period means and sums of squared deviations (and the
        mean over m of |period mean|^2 when known)."""
        level = scale2 * (_mean0(_abs2(mean)) if mean_abs2 is None else mean_abs2)
        noise = None if n_per < 2 else scale2 * _mean0(ss) / (n_per * (n_per - 1)) + floor
        return level, noise

    det_power, det_noise = line_levels(yd, yd_ss, rounding_floor)
    check_finite(output_power, det_power)
    sel = lambda a, s: None if a is None else a[s]        # noqa: E731
    odd_power, even_power = det_power[odd_sel], det_power[even_sel]
    odd_noise, even_noise = sel(det_noise, odd_sel), sel(det_noise, even_sel)

    # Plant-referred: the output's non-excited lines minus the linear response (BLA,
    # interpolated) to the input applied there. A nonlinearity before the measured input
    # (drive output saturation, the loop) leaves nothing; a plant nonlinearity, sensor
    # quantisation or noise remain. The interpolation error (leave-one-out) is added to
    # what is expected there without plant distortion.
    plant_power = plant_expected = plant_bound = g_det = ud_abs2 = None
    n_output_at_noise = 0
    if det_bins.size and excited.size >= 5:
        g_det, loo = _interp_frf(freq, G, det_bins * fs / n)
        e_mean = yd - g_det * ud
        e_ss = yd_ss + _abs2(g_det) * ud_ss - 2 * np.real(np.conj(g_det) * yud)
        plant_power, plant_noise = line_levels(e_mean, np.maximum(e_ss, 0.0), rounding_floor)
        nb = np.clip(np.searchsorted(excited, det_bins), 1, excited.size - 1)
        rel = np.maximum(loo[nb - 1], loo[nb])
        ud_abs2 = _mean0(_abs2(ud))
        g_u = scale2 * _abs2(g_det) * ud_abs2
        plant_bound = rel ** 2 * g_u
        if plant_noise is not None:
            plant_expected = plant_noise + plant_bound
            # A plant distortion is output the plant gives: where the output itself is at
            # its noise (not 6 dB over), what the residual holds is -G U, the linear
            # response to what the input sensor measured there and the plant did not
            # receive (the input's own measurement noise or error): expected, not
            # distortion
            at_noise = det_power <= 4.0 * det_noise
            n_output_at_noise = int(np.sum(at_noise & (plant_power > 4.0 * plant_expected)))
            plant_expected = np.where(at_noise, plant_expected + g_u, plant_expected)
    quant_floor = quant_lines = None
    if y_quantisation_step:
        q = float(y_quantisation_step)
        quant_floor = q ** 2 / (3.0 * n)   # 4 (q^2/12) / N: white, the old model
        if det_bins.size:
            quant_lines = _quantisation_lines(
                q, y_mean_time, mom, is_exc=is_exc, det_i=det_i, g_det=g_det, n=n,
                n_per=n_per, scale2=scale2)

    nu = n_real * (n_per - 1)        # complex degrees of freedom of the noise estimates

    def mean_or_none(x):
        return None if x is None or np.size(x) == 0 else float(np.mean(x))

    out_mean = float(np.mean(output_power))
    nl_mean, noise_mean = mean_or_none(nl_power), mean_or_none(noise_power)
    odd_mean, even_mean = mean_or_none(odd_power), mean_or_none(even_power)
    odd_noise_mean, even_noise_mean = mean_or_none(odd_noise), mean_or_none(even_noise)
    output_db, nl_db, noise_db = to_db(output_power), to_db(nl_power), to_db(noise_power)
    summary = {
        "grid": gridinfo["grid"], "parity_classifiable": gridinfo["parity"],
        # ratios of power sums over the lines (dominated by the strongest lines)
        "nl_re_output_db": _db_ratio(nl_mean, out_mean),
        "noise_re_output_db": _db_ratio(noise_mean, out_mean),
        "noise_re_nl_db": _db_ratio(noise_mean, nl_mean),
        "odd_re_output_db": _db_ratio(odd_mean, out_mean),
        "even_re_output_db": _db_ratio(even_mean, out_mean),
        "odd_re_even_db": _db_ratio(odd_mean, even_mean),
        "odd_re_noise_db": _db_ratio(odd_mean, odd_noise_mean),
        "even_re_noise_db": _db_ratio(even_mean, even_noise_mean),
        "n_var_nl_negative": None if var_nl is None else int(var_nl_negative.sum()),
        # per-line medians: what Figure 3 shows line by line
        "line_median_nl_re_output_db": None if nl_db is None else _median_db(nl_db - output_db),
        "line_median_noise_re_nl_db": None if nl_db is None or noise_db is None else
        _median_db(-(nl_db - noise_db)),
        "line_median_noise_re_output_db": None if noise_db is None else
        _median_db(noise_db - output_db),
        "line_fraction_nl_over_noise_6db": None if nl_power is None or noise_power is None
        else float(np.mean(nl_power > 4.0 * noise_power)),
        "realizations": int(n_real), "periods": int(n_per), "known_reference": bool(known_ref),
    }
    summary.update(excited_stats)
    summary["excited_lines"] = int(excited.size)
    summary.update(_class_stats(odd_power, odd_noise, nu, "odd_"))
    summary.update(_class_stats(even_power, even_noise, nu, "even_"))
    summary.update(_class_stats(det_power, det_noise, nu, "nonexcited_"))
    summary["odd_detected"] = summary["odd_detected"] if gridinfo["parity"] else None
    summary["even_detected"] = summary["even_detected"] if gridinfo["parity"] else None
    summary["nl_detected"] = summary.pop("nonexcited_detected")
    if plant_power is not None:
        floor = 0.0 if quant_lines is None else quant_lines
        exp_q = None if plant_expected is None else plant_expected + floor
        sel_exp = lambda s: None if exp_q is None else exp_q[s]     # noqa: E731
        # the simulated error matches the measured one within about +-6 dB per line (128 ..
        # 4096 counts, tests/bench/bench_detect_matrix.py): a line's excess counts in the
        # single-line test only above 8 times (9 dB) the model
        q_known = quant_lines
        sel_q = lambda s: None if q_known is None else q_known[s]     # noqa: E731
        plant = {}
        plant.update(_class_stats(plant_power[odd_sel], sel_exp(odd_sel), nu, "odd_",
                                  known=sel_q(odd_sel)))
        plant.update(_class_stats(plant_power[even_sel], sel_exp(even_sel), nu, "even_",
                                  known=sel_q(even_sel)))
        plant.update(_class_stats(plant_power, exp_q, nu, "nonexcited_", known=q_known))
        # above the noise and the interpolation error, but not above the quantisation floor
        plant["above_noise_lines"] = (None if plant_expected is None else
                                      int(np.sum(plant_power > 4.0 * plant_expected)))
        with np.errstate(divide="ignore", invalid="ignore"):
            plant["line_median_re_quantisation_floor_db"] = (
                None if quant_lines is None else
                _median_db(10 * np.log10(plant_power / quant_lines)))
        plant["output_at_noise_lines_not_counted"] = n_output_at_noise
        for key, value in plant.items():
            key = key.replace("nonexcited_detected", "nl_detected")
            summary["plant_" + key] = value
        if not gridinfo["parity"]:
            summary["plant_odd_detected"] = summary["plant_even_detected"] = None
    q_level = None if quant_floor is None else \
        quant_floor if quant_lines is None else float(np.mean(quant_lines))
    summary["quantisation_floor_db"] = None if not q_level or q_level <= 0 else \
        float(to_db(q_level))
    summary["quantisation_model"] = (
        None if quant_floor is None else
        "periodic: the error of quantising the predicted output" +
        (" (offset fitted to the samples)" if y_mean_time is not None
         else " (averaged over offsets: no samples)"))
    summary["bands"] = _band_figures(odd_bins, odd_power, odd_noise, even_bins, even_power,
                                     even_noise, det_bins, det_power, det_noise, fs, n,
                                     gridinfo["parity"])

    # the excitation itself at the non-excited lines (a distorted actuator force, ...)
    xname = "reference r" if known_ref else "input u"
    summary["excitation_nonexcited_re_excited_db"] = None
    summary["excitation_nonexcited_top_re_excited_db"] = None
    summary["excitation_distorted"] = None
    if det_bins.size:
        x_det, x_noise = line_levels(xd, xd_ss, mean_abs2=None if known_ref else ud_abs2)
        x_exc = scale2 * (_mean0(_abs2(xe)) if x_exc_abs2 is None else x_exc_abs2)
        # (dB keeps the order: median and quantile from the middle values only)
        x_exc_db = _median_db_of(x_exc)
        rel_db = float(_median_db_of(np.maximum(x_det, 1e-300)) - x_exc_db)
        summary["excitation_nonexcited_re_excited_db"] = rel_db
        # the strongest tenth: an odd distortion of an odd grid leaves the even lines
        # (half of the detection lines) empty, so the median alone can miss it
        top_db = float(_quantile_db_of(np.maximum(x_det, 1e-300), 0.9) - x_exc_db)
        summary["excitation_nonexcited_top_re_excited_db"] = top_db
        if x_noise is not None:
            xs = _class_stats(x_det, x_noise, nu, "x_")
            # rounding of a float32 record is not distortion: 100 dB under the lines
            summary["excitation_distorted"] = bool(xs["x_detected"] and top_db > -100.0)
            if summary["excitation_distorted"]:
                notes.append(
                    f"{xname} is distorted: its non-excited lines lie {rel_db:.1f} dB (median; "
                    f"the strongest tenth {top_db:.1f} dB) under its excited lines ({xs['x_lines_over_noise_6db']} of "
                    f"{det_bins.size} lines 6 dB over their noise): the actuator or an "
                    f"interaction with the structure. The output's non-excited lines then "
                    f"carry the linear response to it too (the plant_* figures remove it)"
                    + ("; give the reference (--columns ...,r=NAME) for a known-reference "
                       "estimate" if not known_ref else ""))
    else:
        if excited_stats["excited_detected"] is None:
            notes.append("no non-excited line between the lowest and the highest excited "
                         "line, and no var_total vs var_noise at the excited lines (needs "
                         "M >= 2 and P >= 2): no nonlinear detection possible with this "
                         "experiment")

    if transient is not None:
        pass                          # (the local polynomial method: checked on the periods)
    elif Y_exc is not None:
        transient = _transient(Y_exc, settle, n_per)
    else:
        transient = TransientCheck(level_db=np.array([]), message="not checked: line moments "
                                   "keep no single period")
        notes.append("transient not checked: the line moments (statistics) keep no single "
                     "period; let the settle periods cover the loop's settling")
    if transient.suspect:
        notes.append(transient.message)
        if warn_transient:     # (called from robust_bla_spectra: point at its caller)
            warnings.warn(transient.message, TransientWarning, stacklevel=3)

    return BLAResult(
        fs=float(fs), n_period=n, bins=excited, freq=freq, G=G,
        var_total=var_total, var_noise=var_noise, var_nl=var_nl,
        var_nl_negative=var_nl_negative, output_db=output_db,
        nl_db=nl_db, noise_db=noise_db,
        odd_bins=odd_bins, odd_db=to_db(odd_power), odd_noise_db=to_db(odd_noise),
        even_bins=even_bins, even_db=to_db(even_power), even_noise_db=to_db(even_noise),
        summary=summary, transient=transient, n_realizations=n_real, n_periods=n_per,
        settle_periods=settle, known_reference=known_ref, notes=notes,
        grid=gridinfo["grid"], nonexcited_bins=det_bins, nonexcited_db=to_db(det_power),
        nonexcited_noise_db=to_db(det_noise), plant_db=to_db(plant_power),
        plant_expected_db=to_db(plant_expected), quantisation_floor_db=summary["quantisation_floor_db"],
        quantisation_db=to_db(quant_lines))


def estimate_quantisation_step(y, max_levels=200000):
    """Quantisation step of a recorded signal (e.g. an encoder angle), or None.

    The distinct values of a quantised signal are integer multiples of its step q: q is
    taken as the median spacing of the sorted distinct values and accepted only when
    every value lies within 2 % of q (plus float32 rounding) of a multiple of it.

    Parameters
    ----------
    y : array_like
        Samples (any shape).
    max_levels : int
        More distinct values than this: not quantised (None).

    Returns
    -------
    float or None
        q in the unit of y.
    """
    v = np.unique(np.asarray(y, dtype=np.float64).ravel())
    v = v[np.isfinite(v)]
    if v.size < 3 or v.size > max_levels:
        return None
    q = float(np.median(np.diff(v)))
    if not q > 0:
        return None
    tol = 0.02 * q + 4 * np.finfo(np.float32).eps * float(np.max(np.abs(v)))
    if np.max(np.abs(v - q * np.round(v / q))) > tol:
        return None
    return q


def _plant_state(summary, cls):
    """'yes' (detected), 'no' (no more lines over the noise than noise gives), 'unsure'
    (some lines over, too few to tell), None (not measured) for a plant_ class."""
    det = summary.get(f"plant_{cls}_detected")
    over = summary.get(f"plant_{cls}_lines_over_noise_6db")
    if det is None or over is None:
        return None
    if det:
        return "yes"
    by_noise = summary.get(f"plant_{cls}_lines_by_noise") or 0.0
    return "no" if over <= max(1.0, 2.0 * by_noise) and over < summary[f"plant_{cls}_lines_needed"] \
        else "unsure"


def level_verdict(summary, saturation_fraction=None, level=None):
    """What one level's detection supports, named by cause.

    The closed-loop figures (output at the non-excited lines) say whether the loop is
    nonlinear; the plant-referred ones (``plant_*``: output minus the BLA times the input
    applied there) say whether the plant is. A class of lines counts as nonlinear when
    more of its lines lie 6 dB over what noise (and the BLA interpolation error, and the
    quantisation floor) explain than noise alone gives with probability 1e-3.

    Parameters
    ----------
    summary : dict
        ``BLAResult.summary`` of the level.
    saturation_fraction : float, optional
        Fraction of the samples at which the drive output (plant input) sat at u_max.
    level : str, optional
        Name of the level for the text (e.g. "3 V rms").

    Returns
    -------
    dict
        ``causes``: list of 'linear', 'plant odd nonlinearity', 'plant even
        nonlinearity', 'plant nonlinearity (parity not classifiable with this grid)',
        'nonlinear distortion (above the band)' (the lines up to 3 times the highest
        excited one where the excitation is clean: a full grid's only detection lines;
        on other grids when the band's detection lines show nothing and these do),
        'nonlinear distortion (excited lines)' (no detection line: the excited lines'
        var_total vs var_noise test), 'unmeasured inputs' (the excited lines spread over
        realizations, the detection lines are clean), 'unmeasured inputs or a scale-free
        nonlinearity' (:func:`bla_levels`: the same nonlinear level re the output at
        every level), 'drive output saturation', 'quantisation floor', 'loop
        nonlinearity outside the plant' (closed loop), 'input distortion (before the
        measured input)' (open loop), 'cannot tell' (with what is missing);
        ``text``: one sentence saying why.
    """
    if summary.get("nl_level_independent"):
        inner = level_verdict(dict(summary, nl_level_independent=False), saturation_fraction,
                              level)
        return {"causes": ["unmeasured inputs or a scale-free nonlinearity"],
                "text": "unmeasured inputs or a scale-free nonlinearity" +
                        (f" at {level}" if level else "") +
                        ": the nonlinear variance keeps the same level re the output at every "
                        "excitation level; a nonlinearity with a scale (friction, saturation, "
                        "a cubic term) changes it, so these figures come from inputs that are "
                        "not measured (MIMO cross-coupling, a realization-dependent "
                        "disturbance) unless the plant's characteristic is piecewise linear "
                        "through zero (e.g. a different gain per direction); the figures alone "
                        "would say: " + inner["text"]}
    at = f" at {level}" if level else ""
    sat = saturation_fraction if saturation_fraction is not None else 0.0
    sat_text = f"drive output saturation{at} ({100 * sat:.2g} % of the samples at u_max)"
    flags = [summary.get(k) for k in ("odd_detected", "even_detected", "nl_detected")]
    exc = summary.get("excited_detected")
    exc_text = ""
    if exc is not None:
        med = summary.get("line_median_nl_re_output_db")
        exc_text = (f"{summary.get('excited_lines_over_noise_6db')} of "
                    f"{summary.get('excited_lines')} excited lines with var_total 6 dB over "
                    f"var_noise ({summary.get('excited_lines_needed')} needed, or one line "
                    f"alone at n p <= 1e-3)"
                    + (f", nonlinear level median {med:+.1f} dB re output" if med is not None
                       else ""))
    if all(f is None for f in flags):
        if exc is True:
            return {"causes": ["nonlinear distortion (excited lines)"],
                    "text": f"nonlinear distortion{at} at the excited lines: {exc_text}; no "
                            f"non-excited line, so no odd/even or plant-referred claim, and "
                            f"inputs that differ between realizations and are not measured "
                            f"(MIMO cross-coupling) look the same on the excited lines: a "
                            f"level dependence (several levels) or a MIMO BLA tells them "
                            f"apart"}
        above = summary.get("above_band_detected")
        if above is True:
            return {"causes": ["nonlinear distortion (above the band)"],
                    "text": f"nonlinear distortion{at} above the band: "
                            f"{summary.get('above_band_lines_over_noise_6db')} of "
                            f"{summary.get('above_band_lines')} lines up to 3 times the highest "
                            f"excited line, where the excitation is clean, 6 dB over the "
                            f"output's noise ({summary.get('above_band_lines_needed')} needed, or "
                            f"one line alone at n p <= 1e-3); a full grid has no non-excited line "
                            f"in the band, so no odd/even or plant-referred claim"}
        if exc is False:
            return {"causes": ["linear"],
                    "text": f"linear{at}: no nonlinear variance above the noise at the excited "
                            f"lines ({exc_text}); no non-excited line"}
        why = []
        if summary.get("periods") == 1:
            why.append("no noise estimate (P = 1 period)")
        if summary.get("realizations") == 1:
            why.append("no nonlinear variance (M = 1 realization)")
        if not summary.get("nonexcited_lines"):
            why.append("no non-excited line in the band")
        if not why:
            why.append("no noise estimate or no non-excited line")
        tail = ""
        if above is False:
            tail = (f"; no distortion above the band either ({summary.get('above_band_lines')} "
                    f"lines where the excitation is clean"
                    + (f"; {summary['above_band_lines_input_content']} others left out: the "
                       f"measured input's own content there, whose linear response reaches "
                       f"the output's noise" if summary.get("above_band_lines_input_content")
                       else "") + ")")
        elif summary.get("above_band_lines_excitation_not_clean"):
            tail = (f"; above the band the excitation itself has content at "
                    f"{summary['above_band_lines_excitation_not_clean']} lines (give the "
                    f"reference r for those)")
        return {"causes": ["cannot tell"], "text": "cannot tell: " + " and ".join(why) + tail}
    loop = any(bool(f) for f in flags)
    open_loop = summary.get("known_reference") is False
    where = "at the output" if open_loop else "in the loop"
    classes = ("odd", "even") if summary.get("parity_classifiable") else ("nonexcited",)
    states = {cls: _plant_state(summary, cls) for cls in classes}
    parts, causes = [], []
    for cls, state in states.items():
        name = (f"plant {cls} nonlinearity" if cls != "nonexcited" else
                "plant nonlinearity (parity not classifiable with this grid)")
        n_over = summary.get(f"plant_{cls}_lines_over_noise_6db")
        n_all = summary.get(f"plant_{cls}_lines")
        lines = "lines" if cls == "nonexcited" else f"{cls} lines"
        if state == "yes":
            causes.append(name)
            med = summary.get(f"plant_{cls}_line_median_re_noise_db")
            parts.append(f"{name.replace(' (parity', ', (parity')} ({n_over} of {n_all} {lines} "
                         f"6 dB over what noise, BLA interpolation and quantisation explain"
                         + (f", median {med:+.1f} dB)" if med is not None else ")"))
        elif state == "unsure" and loop:
            causes.append("cannot tell")
            parts.append(f"cannot tell whether the plant is nonlinear at the {lines}: "
                         f"{n_over} of {n_all} over the noise, "
                         f"{summary[f'plant_{cls}_lines_needed']} needed (more detection lines: "
                         f"a longer period or a wider band)")
    plant_yes = any(s == "yes" for s in states.values())
    if not loop and not plant_yes and summary.get("above_band_detected") is True:
        # the band's detection lines at their noise, the lines above it not: a distortion
        # whose harmonics fall above the band (the in-band lines are too few or the
        # distortion's lines miss them)
        return {"causes": ["nonlinear distortion (above the band)"],
                "text": f"nonlinear distortion{at} above the band: "
                        f"{summary.get('above_band_lines_over_noise_6db')} of "
                        f"{summary.get('above_band_lines')} lines up to 3 times the highest "
                        f"excited line, where the excitation is clean, 6 dB over the "
                        f"output's noise ({summary.get('above_band_lines_needed')} needed, or "
                        f"one line alone at n p <= 1e-3), while the "
                        f"{summary.get('nonexcited_lines')} non-excited lines in the band "
                        f"show none above the noise"}
    if not loop and not plant_yes and exc is True \
            and (summary.get("excited_line_median_re_noise_db") or 0.0) >= 3.0:
        return {"causes": ["unmeasured inputs"],
                "text": f"no distortion{at} at the non-excited lines, yet the realizations "
                        f"spread more than the noise at the excited lines ({exc_text}): a "
                        f"nonlinearity puts distortion on both, so this is the signature of "
                        f"inputs that differ between realizations and are not measured "
                        f"(cross-coupling from other excited inputs of a MIMO system, a "
                        f"realization-dependent disturbance), not of a nonlinearity"}
    if not loop and not plant_yes:
        text = f"linear{at}: no nonlinear distortion above the noise"
        if sat > 0:
            text += f" (though {100 * sat:.2g} % of the samples at u_max)"
        return {"causes": ["linear"], "text": text}
    # lines that are nonlinear in the loop but not referred to the plant: say why
    loop_only = [cls for cls in classes if states[cls] == "no" and
                 summary.get("nl_detected" if cls == "nonexcited" else f"{cls}_detected")]
    if loop and all(s is None for s in states.values()):
        return {"causes": ["cannot tell"],
                "text": f"nonlinear distortion {where}; no plant-referred figures (they need "
                        f">= 5 excited lines and P >= 2) to say whether it comes from the plant"}
    if not plant_yes and "cannot tell" not in causes and not loop_only:
        loop_only = ["nonexcited"]
    if loop_only:
        which = " and ".join("non-excited" if c == "nonexcited" else c for c in loop_only)
        if sat > 0:
            causes.append("drive output saturation")
            parts.append(f"{which} lines: {sat_text}; the distortion enters at the plant "
                         f"input, the plant-referred lines show none above the noise")
        elif summary.get("quantisation_floor_db") is not None:
            causes.append("quantisation floor")
            parts.append(f"{which} lines: distortion at the encoder quantisation floor "
                         f"({summary['quantisation_floor_db']:.1f} dB per line), not above it")
        elif open_loop:
            causes.append("input distortion (before the measured input)")
            parts.append(f"{which} lines: distortion at the output that the plant-referred "
                         f"lines do not show (it comes with the measured input u: the "
                         f"actuator or the generator, not the plant)")
        else:
            causes.append("loop nonlinearity outside the plant")
            parts.append(f"{which} lines: distortion in the loop that the plant-referred "
                         f"lines do not show (it enters at the plant input)")
    elif sat > 0:
        causes.append("drive output saturation")
        parts.append("also " + sat_text)
    if summary.get("parity_classifiable") is False and plant_yes:
        parts.append(f"no odd/even claim: {summary.get('grid')} grid")
    return {"causes": causes, "text": "; ".join(parts)}


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
    notes : list of str
        What the levels say together (a level-independent "nonlinear" variance: the
        signature of unmeasured inputs, not of a nonlinearity).
    """

    rms: np.ndarray
    results: list
    freq: np.ndarray
    G: np.ndarray
    notes: list = field(default_factory=list)


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
    notes = []
    note = level_independence_note(np.array(rms), [res.summary for res in results])
    if note:
        notes.append(note)
        for res in results:
            res.notes.append(note)
            res.summary["nl_level_independent"] = True
    return BLALevels(rms=np.array(rms), results=results, freq=results[0].freq,
                     G=np.stack([res.G for res in results]), notes=notes)


def level_independence_note(rms, summaries, tolerance_db=3.0):
    """A note when the nonlinear variance is detected at every level yet keeps the same
    level re the output (within ``tolerance_db``) over levels spanning 6 dB or more.

    A nonlinearity with a scale changes its distortion re the output with the amplitude
    (a cubic term: +2 dB per dB, Coulomb friction: -1 dB per dB, a saturation from zero
    to large); a variance in fixed proportion to the output at every level is what
    unmeasured inputs give (other excited inputs of a MIMO system coupling into this
    output, a disturbance that changes between realizations) and, among
    nonlinearities, only a scale-free one (piecewise linear through zero). Returns the
    note or None.
    """
    rms = np.asarray(rms, dtype=float)
    if rms.size < 2 or not np.all(rms > 0) or 20 * np.log10(rms.max() / rms.min()) < 6.0:
        return None
    rel = [s.get("nl_re_output_db") for s in summaries]
    det = [s.get("excited_detected") for s in summaries]
    if any(r is None for r in rel) or not all(d is True for d in det):
        return None
    spread = max(rel) - min(rel)
    if spread > tolerance_db:
        return None
    return (f"the nonlinear variance is the same re the output at every level "
            f"({min(rel):+.1f} .. {max(rel):+.1f} dB over {20 * np.log10(rms.max() / rms.min()):.0f} "
            f"dB of excitation): a nonlinearity with a scale (friction, saturation, a cubic term) "
            f"changes its distortion with the level, so this is the signature of inputs that are "
            f"not measured (cross-coupling from other excited inputs of a MIMO system, a "
            f"realization-dependent disturbance), or of a scale-free (piecewise linear through "
            f"zero) characteristic; measure those inputs (a MIMO BLA with M >= n_u "
            f"realizations) to tell")


@dataclass
class MimoBLAResult:
    """Robust MIMO BLA of n_y outputs on n_u inputs (:func:`robust_bla_mimo`).

    Attributes
    ----------
    fs : float
        Sample rate (Hz).
    n_period : int
        Samples per period N.
    bins, freq : ndarray, shape (E,)
        Excited lines (DFT bins, Hz).
    G : ndarray of complex, shape (E, n_y, n_u)
        G_BLA per line (output unit / input unit).
    var_total, var_noise, var_nl : ndarray, shape (E, n_y, n_u), or None
        Per entry, as in :class:`BLAResult` with the blocks of n_u experiments in the role
        of the realizations (``var_total`` needs 2 blocks, ``var_noise`` P >= 2).
    detected : ndarray of bool, shape (n_y, n_u), or None
        Per entry, the excited lines' test (var_total vs var_noise, F(2 (B - 1),
        2 B (P - 1)), 6 dB count or the strongest line after Bonferroni) and the median
        line 3 dB over (the blocks' input matrices differ in conditioning, so the noise of
        G differs between blocks and the F tail alone gives false alarms).
    lines_over_noise_6db : ndarray of int, shape (n_y, n_u), or None
    nl_re_output_db : ndarray, shape (n_y, n_u), or None
        Power ratio of the nonlinear variance times |U|^2 over the output level.
    n_blocks, n_periods : int
    notes : list of str
    """

    fs: float
    n_period: int
    bins: np.ndarray
    freq: np.ndarray
    G: np.ndarray
    var_total: np.ndarray
    var_noise: np.ndarray
    var_nl: np.ndarray
    detected: np.ndarray
    lines_over_noise_6db: np.ndarray
    nl_re_output_db: np.ndarray
    n_blocks: int
    n_periods: int
    notes: list = field(default_factory=list)


def robust_bla_mimo(u, y, *, fs=1.0, settle_periods=0, excited_bins=None):
    """Robust MIMO BLA (known inputs): n_u inputs measured together, M = B n_u
    realizations taken as B blocks of n_u experiments (Pintelon and Schoukens, robust
    method for MIMO systems). Cross-coupling from the other inputs is then part of G, not
    of the nonlinear variance (which a SISO analysis of one input pair reports).

    Per block b, period p and line k the n_u experiments give the square input matrix
    U[b, p, k] (inputs x experiments) and the output matrix Y[b, p, k] (outputs x
    experiments): G[b, p, k] = Y U^-1. Then, per entry, as the SISO robust method with the
    blocks in the role of the realizations: G_b = mean_p, s2n_b = sum_p |G_bp - G_b|^2 /
    (P (P - 1)), G_BLA = mean_b, var_total = sum_b |G_b - G_BLA|^2 / (B (B - 1)),
    var_noise = sum_b s2n_b / B^2, var_nl = B (var_total - var_noise).

    Parameters
    ----------
    u : array_like, shape (M, T + P, N, n_u)
        Inputs; M a multiple of n_u (each block of n_u consecutive realizations must excite
        the inputs independently, e.g. random phases per input and realization).
    y : array_like, shape (M, T + P, N, n_y)
        Outputs.
    fs : float
        Sample rate (Hz).
    settle_periods : int
        T, dropped.
    excited_bins : array_like of int, optional
        Excited bins (all inputs on the same lines); found from the first input's spectrum
        by default.

    Returns
    -------
    MimoBLAResult

    Raises
    ------
    InputError
        Bad shapes, M not a multiple of n_u, a singular input matrix at a line.
    """
    u, y = np.asarray(u), np.asarray(y)
    if u.ndim != 4 or y.ndim != 4 or u.shape[:3] != y.shape[:3]:
        raise InputError(f"MIMO BLA: expected u (M, T+P, N, n_u) and y (M, T+P, N, n_y) with "
                         f"the same M, T+P, N; got {u.shape} and {y.shape}")
    n_real, n_total, n, n_u = u.shape
    n_y = y.shape[3]
    if n_real % n_u or n_real < n_u:
        raise InputError(f"MIMO BLA: M = {n_real} realizations is not a multiple of the "
                         f"n_u = {n_u} inputs (blocks of n_u experiments)")
    fs, settle = check_arguments(fs=fs, n_period=n, settle_periods=settle_periods,
                                 n_total=n_total, hold_text=False)
    # every input's periods checked before averaging; the MIMO layout (blocks of n_u
    # experiments) is not re-inferred: what the SISO estimate would handle is refused
    notes = []
    for i in range(n_u):
        lay = check_blocks(u[..., i], settle_periods=settle, name=f"input {i}", fs=fs,
                           infer=False, mixed_levels="note")
        if lay.changed:
            raise InputError(f"MIMO BLA: {lay.notes[0]}: every experiment must hold the "
                             f"same periods; cut the records to the excited periods")
        notes.extend(lay.notes)
    if excited_bins is None:
        excited = detect_excited_lines(u[..., 0], settle)
    else:
        excited = _validate_lines(excited_bins, n)
    n_blocks, n_per = n_real // n_u, n_total - settle
    # spectra at the excited lines: (M, P, E, channels)
    U = np.take(np.fft.rfft(u[:, settle:], axis=2), excited, axis=2)
    Y = np.take(np.fft.rfft(y[:, settle:], axis=2), excited, axis=2)
    if not (np.isfinite(U).all() and np.isfinite(Y).all()):
        raise InputError("MIMO BLA: NaN or inf in u or y")
    # (B, P, E, channel, experiment)
    Ub = U.reshape(n_blocks, n_u, n_per, excited.size, n_u).transpose(0, 2, 3, 4, 1)
    Yb = Y.reshape(n_blocks, n_u, n_per, excited.size, n_y).transpose(0, 2, 3, 4, 1)
    # G U = Y  <=>  U^T G^T = Y^T
    try:
        cond = np.linalg.cond(Ub)
    except np.linalg.LinAlgError:
        cond = np.full(Ub.shape[:3], np.inf)
    if not np.all(cond < 1e12):
        bad = np.argwhere(~(cond < 1e12))[0]
        raise InputError(f"MIMO BLA: the inputs of block {bad[0]} are not independent at "
                         f"{excited[bad[2]] * fs / n:g} Hz (input matrix singular): excite the "
                         f"inputs with independent phases in each realization")
    Gp = np.linalg.solve(np.swapaxes(Ub, -1, -2), np.swapaxes(Yb, -1, -2))
    Gp = np.swapaxes(Gp, -1, -2)                       # (B, P, E, n_y, n_u)
    G_b = Gp.mean(axis=1)
    G = G_b.mean(axis=0)
    var_total = var_noise = var_nl = detected = over = nl_rel = None
    if n_blocks >= 2:
        var_total = np.sum(np.abs(G_b - G) ** 2, axis=0) / (n_blocks * (n_blocks - 1))
    else:
        notes.append(f"one block of {n_u} experiments: no total or nonlinear variance "
                     f"(needs M >= {2 * n_u})")
    if n_per >= 2:
        s2n = np.sum(np.abs(Gp - G_b[:, None]) ** 2, axis=1) / (n_per * (n_per - 1))
        var_noise = s2n.sum(axis=0) / n_blocks ** 2
    else:
        notes.append("P = 1 period: no noise variance (needs P >= 2)")
    if var_total is not None and var_noise is not None:
        var_nl = n_blocks * (var_total - var_noise)
        d1, d2 = 2 * (n_blocks - 1), 2 * n_blocks * (n_per - 1)
        detected = np.zeros((n_y, n_u), bool)
        over = np.zeros((n_y, n_u), int)
        nl_rel = np.full((n_y, n_u), np.nan)
        u_pow = np.mean(np.abs(U) ** 2, axis=(0, 1))           # (E, n_u)
        y_pow = np.mean(np.abs(Y.mean(axis=1)) ** 2, axis=0)    # (E, n_y)
        for o in range(n_y):
            for i in range(n_u):
                with np.errstate(divide="ignore", invalid="ignore"):
                    st = _class_stats(var_total[:, o, i],
                                      np.where(var_noise[:, o, i] > 0, var_noise[:, o, i], np.nan),
                                      d2 / 2, "x_", tail=lambda x: f_sf_even(x, d1, d2))
                # each block's input matrix has its own conditioning, so the noise of G
                # differs between blocks and the F tail is too light: the median line
                # must also lie 3 dB over (a nonlinearity lifts most lines)
                med = st["x_line_median_re_noise_db"]
                detected[o, i] = bool(st["x_detected"]) and med is not None and med >= 3.0
                over[o, i] = st["x_lines_over_noise_6db"]
                nl = float(np.sum(np.maximum(var_nl[:, o, i], 0) * u_pow[:, i]))
                out = float(np.sum(y_pow[:, o]))
                nl_rel[o, i] = 10 * np.log10(nl / out) if nl > 0 and out > 0 else np.nan
    return MimoBLAResult(fs=float(fs), n_period=n, bins=excited, freq=excited * fs / n, G=G,
                         var_total=var_total, var_noise=var_noise, var_nl=var_nl,
                         detected=detected, lines_over_noise_6db=over, nl_re_output_db=nl_rel,
                         n_blocks=n_blocks, n_periods=n_per, notes=notes)
