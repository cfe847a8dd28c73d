"""Line statistics of sine runs: what the drive accumulates instead of recording samples.

A sine run at bin c of a period of N samples (c cycles per period), P recorded periods.
For a signal x and the harmonics k = 1 .. K the per-period DFT

    X_p[k] = sum_{n=0}^{N-1} x_p[n] exp(-j 2 pi k c n / N)      (numpy rfft at bin k c)

has the mean over periods  mean[k] = (1/P) sum_p X_p[k]  and the period-to-period variance
var[k] = sum_p |X_p[k] - mean[k]|^2 / (P - 1). For the power signals: the mean and the mean
square of x over the recorded samples. These are sufficient for the HOSIDFs (the mean of
the input at k = 1 and of the output at k = 1 .. K: ``hosidf`` sums the P blocks before
its DFT, which is P x mean), their period-to-period spread, and the rms tracking error.

The drive computes them in float32 while the run records (firmware_sim/core/stat.h,
object 0x2041, docs/firmware.md); :func:`harmonic_stats` computes the same numbers from
raw samples in float64, so a run captured both ways can be compared (``capture: both``).

Multisine runs: per line of a host-configured list (object 0x2042) the drive accumulates the
means of the per-period spectra of u, y, r and the period-to-period (co)variances of U and Y
(firmware_sim/core/lstat.h, object 0x2043): :func:`parse_line_stats` reads them,
:func:`line_stats` computes the same from raw samples in float64.
"""
from dataclasses import dataclass, field

import numpy as np

from fftune.analysis.errors import InputError
from fftune.analysis.hosidf import hosidf_from_lines

__all__ = ["SIGNAL_BITS", "HarmonicStats", "parse_stats", "LineStats", "parse_line_stats", "line_stats",
           "line_moments",
           "harmonic_stats", "hosidf_from_stats",
           "period_hosidf_moments", "period_noise_rms", "relative_difference", "STAT_K_MAX",
           "STAT_SIG_MAX"]

# Signal numbers of the drive (firmware_sim/core/drv.h DRV_SIG_*), the bit order of the data.
SIGNAL_BITS = {"reference": 0, "plant_input": 1, "motor_angle": 2, "load_angle": 3, "error": 4}
STAT_K_MAX = 8      # harmonics the drive holds (stat.h)
STAT_SIG_MAX = 3    # signals with harmonic statistics the drive holds
STAT_FLAG_OVERRUN = 0x01  # header status bit: the statistics are invalid (stat.h)


@dataclass
class HarmonicStats:
    """Line statistics of one sine run.

    Attributes
    ----------
    periods : int
        P, the periods accumulated.
    harmonics : int
        K.
    mean : dict
        Signal name -> complex array (K,): mean over periods of the per-period DFT at
        k c, k = 1 .. K (unnormalised sum over N samples).
    var : dict
        Signal name -> array (K,): sum_p |X_p - mean|^2 / (P - 1); NaN when P < 2.
    power_mean, power_msq : dict
        Signal name -> mean and mean square over the recorded samples.
    """

    periods: int
    harmonics: int
    mean: dict = field(default_factory=dict)
    var: dict = field(default_factory=dict)
    power_mean: dict = field(default_factory=dict)
    power_msq: dict = field(default_factory=dict)

    def rms(self, name):
        """Root mean square of a power signal."""
        return float(np.sqrt(self.power_msq[name]))

    def to_dict(self):
        """A YAML/JSON-ready dict (complex as [re, im] pairs); :meth:`from_dict` inverts it."""
        return {"periods": int(self.periods), "harmonics": int(self.harmonics),
                "mean": {k: [[float(z.real), float(z.imag)] for z in v] for k, v in self.mean.items()},
                "var": {k: [float(x) for x in v] for k, v in self.var.items()},
                "power_mean": {k: float(v) for k, v in self.power_mean.items()},
                "power_msq": {k: float(v) for k, v in self.power_msq.items()}}

    @classmethod
    def from_dict(cls, d):
        try:
            return cls(periods=int(d["periods"]), harmonics=int(d["harmonics"]),
                       mean={k: np.array([complex(a, b) for a, b in v]) for k, v in d["mean"].items()},
                       var={k: np.asarray(v, dtype=float) for k, v in d["var"].items()},
                       power_mean={k: float(v) for k, v in d["power_mean"].items()},
                       power_msq={k: float(v) for k, v in d["power_msq"].items()})
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"statistics: malformed statistics block ({exc})") from None


def _names(mask):
    return [n for n, b in sorted(SIGNAL_BITS.items(), key=lambda kv: kv[1]) if mask >> b & 1]


def parse_stats(data):
    """The drive's statistics data (object 0x2041, little-endian) as :class:`HarmonicStats`.

    Layout: u32 P; u8 K, u8 harmonic signal mask, u8 power signal mask, u8 status (bit 0:
    the drive's background task fell behind its control interrupt, the run's statistics are
    invalid and P is 0; firmware_sim/core/stat.h); per harmonic
    signal (bit order), per k: f32 mean re, f32 mean im, f32 variance (0 when P < 2); per
    power signal: f32 mean, f32 mean square.

    Raises
    ------
    InputError
        Too short, inconsistent length, more than the drive can hold, or marked invalid by
        the drive (status bit 0).
    """
    data = bytes(data)
    if len(data) < 8:
        raise InputError(f"statistics data: {len(data)} bytes, need at least the 8-byte header")
    periods = int.from_bytes(data[0:4], "little")
    k, hmask, pmask, status = data[4], data[5], data[6], data[7]
    if status & STAT_FLAG_OVERRUN:
        raise InputError("statistics data: invalid, the drive's background task fell behind its control "
                         "loop during the run (status bit 0, overrun counter 0x2040:6); capture raw or "
                         "repeat the run")
    if status:
        raise InputError(f"statistics data: unknown status bits 0x{status:02X} in the header")
    hs, ps = _names(hmask), _names(pmask)
    if k > STAT_K_MAX or len(hs) > STAT_SIG_MAX or (hmask | pmask) > 0x1F:
        raise InputError(f"statistics data: header K = {k}, masks 0x{hmask:02X}/0x{pmask:02X} "
                         f"beyond what the drive holds (K <= {STAT_K_MAX}, <= {STAT_SIG_MAX} signals)")
    expected = 8 + 12 * k * len(hs) + 8 * len(ps)
    if len(data) != expected:
        raise InputError(f"statistics data: {len(data)} bytes, the header (K = {k}, "
                         f"{len(hs)} harmonic and {len(ps)} power signals) needs {expected}")
    f = np.frombuffer(data[8:], dtype="<f4").astype(np.float64)
    out = HarmonicStats(periods=periods, harmonics=k)
    pos = 0
    for name in hs:
        blk = f[pos:pos + 3 * k].reshape(k, 3)
        pos += 3 * k
        out.mean[name] = blk[:, 0] + 1j * blk[:, 1]
        out.var[name] = blk[:, 2] if periods > 1 else np.full(k, np.nan)
    for name in ps:
        out.power_mean[name] = float(f[pos])
        out.power_msq[name] = float(f[pos + 1])
        pos += 2
    return out


def harmonic_stats(signals, *, n, cycles, harmonics, power=()):
    """The drive's line statistics computed from raw samples, in float64.

    Parameters
    ----------
    signals : dict
        Name -> array of P x N samples (the recorded periods).
    n : int
        Period N in samples.
    cycles : int
        Sine cycles per period (its bin c).
    harmonics : int
        K; the lines k c, k = 1 .. K, must lie below N / 2.
    power : sequence of str
        Names whose mean and mean square are also wanted (may include names not among the
        harmonic ones; all must be in ``signals``).

    Returns
    -------
    HarmonicStats
        Harmonic statistics for every name in ``signals``.
    """
    n, cycles, harmonics = int(n), int(cycles), int(harmonics)
    if cycles < 1 or harmonics < 1 or 2 * harmonics * cycles >= n:
        raise InputError(f"harmonic statistics: line K c = {harmonics} x {cycles} must lie in "
                         f"1 .. N/2 - 1 = {n // 2 - 1}")
    bins = cycles * np.arange(1, harmonics + 1)
    out = HarmonicStats(periods=0, harmonics=harmonics)
    for name, x in signals.items():
        x = np.asarray(x, dtype=np.float64)
        if x.ndim != 1 or x.size == 0 or x.size % n:
            raise InputError(f"signal '{name}': {x.size} samples is not a whole number of "
                             f"periods of N = {n}")
        blocks = x.reshape(-1, n)
        X = np.fft.rfft(blocks, axis=-1)[:, bins]        # (P, K)
        p = blocks.shape[0]
        out.periods = p
        out.mean[name] = X.mean(axis=0)
        d = X - out.mean[name]
        out.var[name] = (np.sum(d.real ** 2 + d.imag ** 2, axis=0) / (p - 1)) if p > 1 else \
            np.full(harmonics, np.nan)
    for name in power:
        if name not in signals:
            raise InputError(f"power statistics: no signal '{name}'")
        x = np.asarray(signals[name], dtype=np.float64)
        out.power_mean[name] = float(x.mean())
        out.power_msq[name] = float(np.mean(x ** 2))
    return out


def hosidf_from_stats(u_stats, y_stats, *, u_name, y_name, fs, n, cycles, n_harmonics=None):
    """HOSIDFs from line statistics: the same :class:`fftune.analysis.hosidf.HosidfResult`
    as :func:`fftune.analysis.hosidf.hosidf` on the raw samples of the same runs.

    Parameters
    ----------
    u_stats, y_stats : HarmonicStats or nested sequences of them
        Per experiment (any leading axes, last axis the R repeats); usually the same
        objects (one run holds both signals).
    u_name, y_name : str
        Input and output signal names.
    fs : float
        Sample rate (Hz).
    n : int
        Period N.
    cycles : int or array_like of int
        The sine's bin c, broadcast over the leading axes (all but the repeats).
    n_harmonics : int, optional
        K (default: all the statistics hold).

    Returns
    -------
    HosidfResult
    """
    us = np.asarray(u_stats, dtype=object)
    ys = np.asarray(y_stats, dtype=object)
    if us.ndim == 0:
        us, ys = us.reshape(1), ys.reshape(1)
    if us.shape != ys.shape:
        raise InputError(f"statistics: input shape {us.shape} differs from output {ys.shape}")
    flat_u, flat_y = us.ravel(), ys.ravel()
    k = n_harmonics or min(s.harmonics for s in flat_y)
    for s_u, s_y in zip(flat_u, flat_y):
        if u_name not in s_u.mean:
            raise InputError(f"statistics: no harmonic statistics of the input '{u_name}'")
        if y_name not in s_y.mean:
            raise InputError(f"statistics: no harmonic statistics of the output '{y_name}'")
        if s_y.harmonics < k:
            raise InputError(f"statistics: {s_y.harmonics} harmonics recorded, {k} asked for")
    periods = {int(s.periods) for s in flat_y}
    if len(periods) != 1 or 0 in periods:
        raise InputError(f"statistics: runs with different or zero period counts {sorted(periods)}")
    p = periods.pop()
    # the sum over periods (= P x mean) is what hosidf's block sum gives
    U1 = np.array([s.mean[u_name][0] for s in flat_u]).reshape(us.shape) * p
    Yk = np.array([s.mean[y_name][:k] for s in flat_y]).reshape(ys.shape + (k,)) * p
    bins = np.broadcast_to(np.asarray(cycles, dtype=np.int64), us.shape[:-1]).copy()
    return hosidf_from_lines(U1, Yk, bins, n=int(n), n_blocks=p, fs=fs)


def period_hosidf_moments(stats, *, u_name, y_name, n_harmonics=None, max_input_variance=1e-6):
    """Mean HOSIDFs of one sine run and the period-to-period variance of one period's
    HOSIDFs, from its line statistics (for :meth:`fftune.analysis.tuning.KfcSearch.tell_moments`).

    With an input that repeats exactly every period (the drive's generated reference:
    the same samples each period), one period's HOSIDF is
    H_p,k = Y_p[k] exp(-j k angle(U[1])) / |U[1]|, so its mean is the HOSIDF of the run
    (:func:`hosidf_from_stats`) and E|H_p,k - H_k|^2 = var(Y[k]) / |U[1]|^2.

    Parameters
    ----------
    stats : HarmonicStats
        One run, with harmonic statistics of ``u_name`` and ``y_name`` and P >= 2.
    u_name, y_name : str
    n_harmonics : int, optional
        K (default: all the statistics hold).
    max_input_variance : float
        Largest var(U[1]) / |U[1]|^2 accepted as "exactly periodic" (float32 rounding).

    Returns
    -------
    H : ndarray of complex, shape (K,)
    H_var : ndarray, shape (K,)
    n_periods : int

    Raises
    ------
    InputError
        Missing signals, fewer than 2 periods, no input at the sine's line, or an input
        that changes from period to period (its variance would be neglected).
    """
    for name in (u_name, y_name):
        if name not in stats.mean:
            raise InputError(f"statistics: no harmonic statistics of '{name}'")
    k = int(n_harmonics or stats.harmonics)
    if stats.harmonics < k:
        raise InputError(f"statistics: {stats.harmonics} harmonics recorded, {k} asked for")
    if stats.periods < 2:
        raise InputError(f"statistics: {stats.periods} recorded period(s); the period-to-period "
                         "variance needs >= 2")
    u1 = complex(stats.mean[u_name][0])
    if not np.isfinite(u1) or abs(u1) == 0:
        raise InputError(f"input '{u_name}': zero power at the sine frequency")
    rel_var_u = float(stats.var[u_name][0]) / abs(u1) ** 2
    if not rel_var_u <= max_input_variance:
        raise InputError(f"input '{u_name}': changes from period to period (variance {rel_var_u:.3g} "
                         f"of its power at the sine's line, above {max_input_variance:g}); the "
                         "HOSIDF variance from statistics needs an exactly periodic input (the "
                         "drive's reference)")
    harmonics = np.arange(1, k + 1)
    H = np.asarray(stats.mean[y_name][:k]) * np.exp(-1j * harmonics * np.angle(u1)) / abs(u1)
    H_var = np.asarray(stats.var[y_name][:k], dtype=float) / abs(u1) ** 2
    return H, H_var, int(stats.periods)


def period_noise_rms(stats, name, n):
    """Period-to-period rms of a signal per sample, from the variances at its harmonic lines.

    For white noise of variance sigma^2 per sample, each line of the N-sample DFT varies
    from period to period with E|X_p - mean|^2 = N sigma^2; the estimate is
    sqrt(mean_k var[k] / N). From raw samples the same quantity is the spread of the
    samples over the periods (what the raw tune path computes); the two agree for white
    measurement noise. Lines that also carry non-periodic nonlinear motion (stick-slip)
    count it as noise, as the raw spread does.

    Parameters
    ----------
    stats : HarmonicStats
    name : str
    n : int
        Period N in samples.

    Returns
    -------
    float
        Signal unit (e.g. rad); NaN when P < 2.
    """
    if name not in stats.var:
        raise InputError(f"statistics: no harmonic statistics of '{name}'")
    v = np.asarray(stats.var[name], dtype=float)
    if stats.periods < 2 or not np.all(np.isfinite(v)):
        return float("nan")
    return float(np.sqrt(np.mean(v) / int(n)))


def relative_difference(a, b, scale=None):
    """max |a - b| / scale, scale = max |b| unless given: the relative difference of two
    sets of lines on the scale of the largest (how the acceptance of the drive's float32
    statistics against float64 is stated)."""
    a, b = np.asarray(a), np.asarray(b)
    s = np.max(np.abs(b)) if scale is None else scale
    return float(np.max(np.abs(a - b)) / s) if s > 0 else float(np.max(np.abs(a - b)))


# ---- multisine line statistics (object 0x2042 line list, 0x2043 data; core/lstat.h) ----

LSTAT_LINES_MAX = 1024  # lines the drive_sim build holds (0x2040:9 tells a drive's own limit)
LSTAT_LINE_FLOATS = 10


@dataclass
class LineStats:
    """Line statistics of one periodic (multisine) run, per line of the configured list.

    Attributes
    ----------
    periods : int
        P, the recorded periods accumulated.
    bins : ndarray of int, shape (L,)
        DFT bins of the lines.
    U, Y, R : ndarray of complex, shape (L,)
        Means over periods of the per-period DFT (numpy ``rfft`` scaling, no 1/N) of the
        plant input u, the motor angle y and the reference r.
    var_u, var_y : ndarray, shape (L,)
        sum_p |X_p - mean|^2 / (P - 1); NaN when P < 2.
    cov_yu : ndarray of complex, shape (L,)
        sum_p (Y_p - mean Y) conj(U_p - mean U) / (P - 1); NaN when P < 2.
    saturated_samples : int or None
        Recorded samples whose plant input sat at the drive's limit (object 0x2040:11),
        None when not known.
    """

    periods: int
    bins: np.ndarray
    U: np.ndarray
    Y: np.ndarray
    R: np.ndarray
    var_u: np.ndarray
    var_y: np.ndarray
    cov_yu: np.ndarray
    saturated_samples: int = None

    def to_dict(self):
        """A JSON-ready dict (complex as [re, im] pairs, NaN as None); :meth:`from_dict`
        inverts it."""
        def real(v):
            return [float(x) if np.isfinite(x) else None for x in np.asarray(v, dtype=float)]

        def cplx(v):
            return [[float(z.real), float(z.imag)] if np.isfinite(z) else None for z in np.asarray(v)]
        return {"periods": int(self.periods), "bins": [int(b) for b in self.bins],
                "U": cplx(self.U), "Y": cplx(self.Y), "R": cplx(self.R), "var_u": real(self.var_u),
                "var_y": real(self.var_y), "cov_yu": cplx(self.cov_yu),
                "saturated_samples": None if self.saturated_samples is None else int(self.saturated_samples)}

    @classmethod
    def from_dict(cls, d):
        def real(v):
            return np.array([np.nan if x is None else float(x) for x in v])

        def cplx(v):
            return np.array([complex(np.nan, np.nan) if z is None else complex(z[0], z[1]) for z in v])
        try:
            out = cls(periods=int(d["periods"]), bins=np.asarray(d["bins"], dtype=np.int64),
                      U=cplx(d["U"]), Y=cplx(d["Y"]), R=cplx(d["R"]), var_u=real(d["var_u"]),
                      var_y=real(d["var_y"]), cov_yu=cplx(d["cov_yu"]))
            sat = d.get("saturated_samples")
            out.saturated_samples = None if sat is None else int(sat)
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise InputError(f"line statistics: malformed block ({exc})") from None
        if any(np.shape(getattr(out, k)) != out.bins.shape for k in ("U", "Y", "R", "var_u", "var_y", "cov_yu")):
            raise InputError(f"line statistics: malformed block (arrays of other lengths than "
                             f"the {out.bins.size} bins)")
        return out


def parse_line_stats(data):
    """The drive's line statistics (object 0x2043, little-endian) as :class:`LineStats`.

    Layout: u32 P; u16 L; u8 status; u8 0; per line: u32 bin; f32 mean U re, im, mean Y
    re, im, mean R re, im, var U, var Y, cov YU re, im (variances and covariance over
    periods with 1 / (P - 1), 0 when P < 2).

    Raises
    ------
    InputError
        Too short, a length that does not match L, an unknown status, or bins that are not
        strictly ascending and positive.
    """
    data = bytes(data)
    if len(data) < 8:
        raise InputError(f"line statistics data: {len(data)} bytes, need at least the 8-byte header")
    periods = int.from_bytes(data[0:4], "little")
    nlines = int.from_bytes(data[4:6], "little")
    status, pad = data[6], data[7]
    if status or pad:
        raise InputError(f"line statistics data: unknown status 0x{status:02X}/0x{pad:02X} in the header")
    expected = 8 + (4 + 4 * LSTAT_LINE_FLOATS) * nlines
    if len(data) != expected:
        raise InputError(f"line statistics data: {len(data)} bytes, the header's {nlines} lines need {expected}")
    rec = np.frombuffer(data[8:], dtype=np.dtype([("bin", "<u4"), ("v", "<f4", (LSTAT_LINE_FLOATS,))]))
    bins = rec["bin"].astype(np.int64)
    if bins.size and (bins[0] < 1 or np.any(np.diff(bins) <= 0)):
        raise InputError("line statistics data: bins not strictly ascending from 1")
    v = rec["v"].astype(np.float64)
    nan = np.full(nlines, np.nan)
    many = periods > 1
    return LineStats(periods=periods, bins=bins, U=v[:, 0] + 1j * v[:, 1], Y=v[:, 2] + 1j * v[:, 3],
                     R=v[:, 4] + 1j * v[:, 5], var_u=v[:, 6] if many else nan,
                     var_y=v[:, 7] if many else nan,
                     cov_yu=(v[:, 8] + 1j * v[:, 9]) if many else nan + 0j)


def line_stats(u, y, r, *, n, bins):
    """The drive's line statistics computed from raw samples, in float64.

    Parameters
    ----------
    u, y, r : array_like, shape (P * N,)
        Plant input, motor angle and reference of the recorded periods.
    n : int
        Period N in samples.
    bins : array_like of int
        The lines (DFT bins, 1 <= bin < N/2).

    Returns
    -------
    LineStats
    """
    n = int(n)
    bins = np.asarray(bins, dtype=np.int64).reshape(-1)
    if bins.size and (bins.min() < 1 or 2 * bins.max() >= n):
        raise InputError(f"line statistics: bins must lie in 1 .. N/2 - 1 = {n // 2 - 1}")
    spec = {}
    for name, x in (("u", u), ("y", y), ("r", r)):
        x = np.asarray(x, dtype=np.float64).reshape(-1)
        if x.size == 0 or x.size % n:
            raise InputError(f"line statistics: {name} has {x.size} samples, not a whole number of periods of {n}")
        spec[name] = np.fft.rfft(x.reshape(-1, n), axis=1)[:, bins]
    periods = spec["u"].shape[0]
    mean = {k: v.mean(axis=0) for k, v in spec.items()}
    du, dy = spec["u"] - mean["u"], spec["y"] - mean["y"]
    if periods > 1:
        var_u = np.sum(np.abs(du) ** 2, axis=0) / (periods - 1)
        var_y = np.sum(np.abs(dy) ** 2, axis=0) / (periods - 1)
        cov_yu = np.sum(dy * np.conj(du), axis=0) / (periods - 1)
    else:
        var_u = var_y = np.full(bins.size, np.nan)
        cov_yu = var_u + 0j
    return LineStats(periods=periods, bins=bins, U=mean["u"], Y=mean["y"], R=mean["r"], var_u=var_u,
                     var_y=var_y, cov_yu=cov_yu)


def line_moments(stats, *, reference=None):
    """The line moments of M realizations (:class:`fftune.analysis.bla.LineMoments`, what
    :func:`fftune.analysis.bla.robust_bla_moments` reads) from their line statistics.

    Parameters
    ----------
    stats : sequence of LineStats
        One per realization, all with the same lines and periods.
    reference : array_like of complex, shape (M, L), optional
        The reference's spectrum at the lines per realization, replacing the statistics'
        mean R: the excitation the host generated (a disturbance added at the plant input
        is not what the drive records as its reference). The reference is taken as exactly
        periodic either way (the drive plays it from its table).

    Returns
    -------
    LineMoments
    """
    from fftune.analysis.bla import LineMoments

    stats = list(stats)
    if not stats:
        raise InputError("line statistics: no realization")
    first = stats[0]
    for m, st in enumerate(stats):
        if st.periods != first.periods or not np.array_equal(st.bins, first.bins):
            raise InputError(f"line statistics of realization {m}: {st.periods} periods at "
                             f"{st.bins.size} lines, realization 0 has {first.periods} at "
                             f"{first.bins.size} (the same lines and periods are needed)")
    p = int(first.periods)
    if p < 1:
        raise InputError("line statistics: 0 periods accumulated")
    for m, st in enumerate(stats):
        values = [st.U, st.Y, st.R] + ([st.var_u, st.var_y, st.cov_yu] if p > 1 else [])
        bad = ~np.all([np.isfinite(v) for v in values], axis=0)
        if bad.any():
            raise InputError(f"line statistics of realization {m}: non-finite values at "
                             f"{int(bad.sum())} line(s), first bin {int(st.bins[bad][0])} "
                             f"(the drive's float32 sums overflowed, or the data are corrupt)")

    def stack(name):
        return np.stack([np.asarray(getattr(st, name)) for st in stats])

    # sums of squared deviations: (P - 1) x the drive's variance (none with P = 1)
    k = float(p - 1)
    if p > 1:
        ss_u, ss_y, s_yu = k * stack("var_u"), k * stack("var_y"), k * stack("cov_yu")
    else:
        shape = (len(stats), first.bins.size)
        ss_u, ss_y, s_yu = np.zeros(shape), np.zeros(shape), np.zeros(shape, complex)
    R = stack("R") if reference is None else np.asarray(reference, dtype=complex)
    if R.shape != (len(stats), first.bins.size):
        raise InputError(f"line statistics: reference spectra of shape {R.shape}, expected "
                         f"({len(stats)}, {first.bins.size}) (realizations, lines)")
    return LineMoments(bins=first.bins, n_periods=p, U=stack("U"), Y=stack("Y"), ss_u=ss_u,
                       ss_y=ss_y, s_yu=s_yu, R=R, ss_r=None)
