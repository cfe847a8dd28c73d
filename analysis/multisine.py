"""Random odd (and odd, full) multisine excitation design.

Two entry points:

* :func:`drive_multisine` implements the on-drive algorithm of ``docs/multisine.md``
  exactly (same xorshift32 PRNG, same line removal, same phases, flat amplitudes). The
  firmware tests compare the C table with it; keep its signature stable.
* :func:`design_multisine` is the general designer (band in Hz or bins, kinds
  ``'random_odd'``, ``'odd'``, ``'full'``, user amplitude spectrum, rms scaling,
  optional crest-factor reduction). For ``kind='random_odd'`` with a flat spectrum and no
  crest-factor reduction it returns exactly what the drive plays.

Frequencies are DFT bins k of one period of ``n_period`` samples: f = k * fs / n_period.
"""
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from fftune.analysis.errors import InputError

__all__ = [
    "Multisine", "LineSet", "fmix32", "stream_init", "xorshift32", "uniform01",
    "index_below", "drive_lines", "drive_phases", "drive_multisine", "design_multisine",
    "multisine_realizations", "random_odd_multisine", "crest_factor", "synthesize_period",
]

_MASK32 = 0xFFFFFFFF
_GOLDEN32 = 0x9E3779B9


# --------------------------------------------------------------------------- PRNG
def fmix32(z):
    """MurmurHash3 32-bit finaliser (docs/multisine.md), on an unsigned 32-bit integer."""
    z &= _MASK32
    z ^= z >> 16
    z = (z * 0x85EBCA6B) & _MASK32
    z ^= z >> 13
    z = (z * 0xC2B2AE35) & _MASK32
    z ^= z >> 16
    return z


def stream_init(seed, stream):
    """Initial xorshift32 state of PRNG stream ``stream`` for ``seed`` (never 0)."""
    x = fmix32((int(seed) + int(stream) * _GOLDEN32) & _MASK32)
    return x if x != 0 else 0x6D2B79F5


def xorshift32(x):
    """One xorshift32 step (Marsaglia 2003); returns the new state (= the output)."""
    x ^= (x << 13) & _MASK32
    x ^= x >> 17
    x ^= (x << 5) & _MASK32
    return x


def uniform01(x):
    """Map a PRNG output to [0, 1): (x >> 8) * 2**-24 (exact in float32)."""
    return (x >> 8) * (2.0 ** -24)


def index_below(x, n):
    """Map a PRNG output to an integer in [0, n): (x * n) >> 32."""
    return (x * n) >> 32


# --------------------------------------------------------------------------- lines
class LineSet(NamedTuple):
    """Bin index arrays (int64, ascending) of a multisine design.

    excited : bins carrying power.
    removed : odd candidates left out by the random-odd group rule (detection lines).
    detection_odd : non-excited odd bins in [k_min, k_max] (removed ones included).
    even : non-excited even bins in [k_min, k_max].
    """

    excited: np.ndarray
    removed: np.ndarray
    detection_odd: np.ndarray
    even: np.ndarray


def _check_band(n_period, k_min, k_max):
    if int(n_period) != n_period or n_period < 4:
        raise InputError(f"multisine: n_period must be an integer >= 4, got {n_period}")
    if not (1 <= k_min <= k_max < n_period / 2):
        raise InputError(
            f"multisine: band in bins must satisfy 1 <= k_min <= k_max < n_period/2, "
            f"got k_min={k_min}, k_max={k_max}, n_period={n_period}")


def _line_set(excited, removed, k_min, k_max):
    excited = np.asarray(excited, dtype=np.int64)
    bins = np.arange(k_min, k_max + 1, dtype=np.int64)
    non_excited = np.setdiff1d(bins, excited)
    return LineSet(excited=excited, removed=np.asarray(removed, dtype=np.int64),
                   detection_odd=non_excited[non_excited % 2 == 1],
                   even=non_excited[non_excited % 2 == 0])


def drive_lines(n_period, k_min, k_max, group, seed):
    """Line sets of the on-drive random odd multisine (docs/multisine.md, "Lines").

    Parameters
    ----------
    n_period : int
        Samples per period N.
    k_min, k_max : int
        Band in DFT bins, inclusive, 1 <= k_min <= k_max < N/2.
    group : int
        Group size G of consecutive odd candidates of which one is removed at random;
        0 removes none.
    seed : int
        uint32 seed; the line set depends on it only (same for every realization).

    Returns
    -------
    LineSet
    """
    _check_band(n_period, k_min, k_max)
    if group != 0 and not 2 <= group <= 16:
        raise InputError(f"multisine: group must be 0 or 2..16, got {group}")
    first_odd = k_min if k_min % 2 else k_min + 1
    candidates = list(range(first_odd, k_max + 1, 2))
    removed = []
    if group >= 2:
        x = stream_init(seed, 0)
        for g in range(len(candidates) // group):
            x = xorshift32(x)
            removed.append(candidates[g * group + index_below(x, group)])
    removed_set = set(removed)
    excited = [c for c in candidates if c not in removed_set]
    return _line_set(excited, removed, k_min, k_max)


def drive_phases(n_lines, seed, realization):
    """Phases (rad, in [-pi, pi)) of realization ``realization``: stream m + 1."""
    x = stream_init(seed, int(realization) + 1)
    phases = np.empty(int(n_lines))
    for i in range(int(n_lines)):
        x = xorshift32(x)
        phases[i] = np.pi * (2.0 * uniform01(x) - 1.0)
    return phases


def synthesize_period(n_period, bins, amplitudes, phases_rad):
    """One period u[n] = sum_i a_i sin(2 pi k_i n / N + phi_i), n = 0..N-1 (float64).

    Computed with an inverse real FFT (exact up to rounding).
    """
    spectrum = np.zeros(int(n_period) // 2 + 1, dtype=complex)
    # sin(x + phi) = Re(exp(j (x + phi - pi/2))); irfft scales by 2/N for 0 < k < N/2.
    spectrum[np.asarray(bins)] = (n_period / 2.0) * np.asarray(amplitudes) * np.exp(
        1j * (np.asarray(phases_rad) - np.pi / 2))
    return np.fft.irfft(spectrum, n=int(n_period))


def drive_multisine(n_period, k_min, k_max, group, seed, realization, rms):
    """One period of the on-drive random odd multisine, float64 (docs/multisine.md).

    Parameters
    ----------
    n_period : int
        Samples per period N.
    k_min, k_max : int
        Band in DFT bins, inclusive.
    group : int
        Detection group size G (0 or 2..16).
    seed, realization : int
        uint32 seed and realization index m.
    rms : float
        rms value of the period (same unit as the returned samples).

    Returns
    -------
    ndarray, shape (n_period,)
        u[n] = sum_i a sin(2 pi e_i n / N + phi_i), a = rms * sqrt(2 / E).
        The line sets are given by :func:`drive_lines` with the same arguments.
    """
    if not np.isfinite(rms) or rms < 0:
        raise InputError(f"multisine: rms must be finite and >= 0, got {rms}")
    lines = drive_lines(n_period, k_min, k_max, group, seed)
    n_exc = lines.excited.size
    if n_exc == 0:
        raise InputError(f"multisine: no excited line in bins [{k_min}, {k_max}]")
    phases = drive_phases(n_exc, seed, realization)
    amp = rms * np.sqrt(2.0 / n_exc)
    return synthesize_period(n_period, lines.excited, np.full(n_exc, amp), phases)


# --------------------------------------------------------------------------- designer
@dataclass(frozen=True)
class Multisine:
    """One realization of a multisine design.

    Attributes
    ----------
    period : ndarray, shape (n_period,)
        One period of the signal, float64 (what the drive plays).
    excited, detection_odd, even, removed : ndarray of int
        DFT bins: excited lines, non-excited odd lines in the band (detection lines),
        non-excited even lines in the band, odd lines removed by the group rule.
    phases : ndarray
        Phase (rad) of each excited line, sin convention as in :func:`synthesize_period`.
    amplitudes : ndarray
        Amplitude (signal unit, peak) of each excited line.
    fs : float
        Sample rate (Hz).
    n_period : int
        Samples per period N; f0 = fs / N.
    realization, seed : int
        Realization index and seed that produced the phases.
    kind : str
        'random_odd', 'odd' or 'full'.
    """

    period: np.ndarray
    excited: np.ndarray
    detection_odd: np.ndarray
    even: np.ndarray
    removed: np.ndarray
    phases: np.ndarray
    amplitudes: np.ndarray
    fs: float
    n_period: int
    realization: int
    seed: int
    kind: str

    @property
    def f0(self):
        """Frequency resolution fs / n_period (Hz)."""
        return self.fs / self.n_period

    @property
    def freq_excited(self):
        """Excited frequencies (Hz)."""
        return self.excited * self.f0

    @property
    def rms(self):
        """rms value of the period."""
        return float(np.sqrt(np.mean(self.period ** 2)))


def crest_factor(x):
    """Crest factor max|x| / rms(x) of a signal (dimensionless)."""
    x = np.asarray(x, dtype=float)
    return float(np.max(np.abs(x)) / np.sqrt(np.mean(x ** 2)))


def _reduce_crest_factor(n_period, bins, amplitudes, phases, iterations):
    """Clip-and-restore crest-factor reduction keeping lines and amplitudes.

    Each iteration clips the signal at a level below its peak, then keeps only the
    phases of the clipped signal's spectrum at the excited lines (amplitudes and line
    set are restored exactly). The best (lowest crest factor) phases are returned.
    """
    best_phases = phases.copy()
    best = crest_factor(synthesize_period(n_period, bins, amplitudes, phases))
    for it in range(int(iterations)):
        x = synthesize_period(n_period, bins, amplitudes, phases)
        peak = np.max(np.abs(x))
        rms = np.sqrt(np.mean(x ** 2))
        # clip level moves from 0.9 peak towards 1.2 rms: strong first, gentle later
        level = max(1.2 * rms, peak * (0.9 - 0.4 * it / max(iterations, 1)))
        spectrum = np.fft.rfft(np.clip(x, -level, level))[bins]
        phases = np.angle(spectrum) + np.pi / 2
        phases = (phases + np.pi) % (2 * np.pi) - np.pi
        cf = crest_factor(synthesize_period(n_period, bins, amplitudes, phases))
        if cf < best:
            best, best_phases = cf, phases.copy()
    return best_phases


def design_multisine(fs, n_period, *, f_min=None, f_max=None, k_min=None, k_max=None,
                     kind="random_odd", group=5, rms=1.0, amplitude_spectrum=None,
                     seed=0, realization=0, crest_factor_iterations=0):
    """Design one realization of a multisine.

    Parameters
    ----------
    fs : float
        Sample rate (Hz).
    n_period : int
        Samples per period N; frequency resolution f0 = fs / N (Hz).
    f_min, f_max : float, optional
        Band (Hz), inclusive; converted to bins ceil(f_min/f0) .. floor(f_max/f0),
        clipped to 1 .. ceil(N/2) - 1 (f_min = 0, f_max = fs/2 mean "all"); f_max above
        fs/2 is an InputError.
    k_min, k_max : int, optional
        Band directly in DFT bins (instead of f_min, f_max). Default 1 .. N/2 - 1.
    kind : {'random_odd', 'odd', 'full'}
        'random_odd': odd bins, one removed at random in each full group of ``group``
        consecutive odd candidates (docs/multisine.md); 'odd': every odd bin;
        'full': every bin of the band.
    group : int
        Group size G for 'random_odd' (0 or 2..16; default 5 as in the paper).
    rms : float
        rms value of the period (signal unit).
    amplitude_spectrum : callable or array_like, optional
        Relative amplitude per excited line: a function of frequency (Hz) or an array
        with one value per excited line. Flat if omitted. Scaled to ``rms``.
    seed : int
        uint32 seed: the line set depends on it only, phases on (seed, realization).
    realization : int
        Realization index m; M realizations are m = 0 .. M-1 (see
        :func:`multisine_realizations`).
    crest_factor_iterations : int
        If > 0, clip-and-restore iterations that lower the crest factor by changing the
        phases only (lines and amplitudes kept; the result then differs from the drive's
        own table, so upload it rather than the seed).

    Returns
    -------
    Multisine
        For ``kind='random_odd'``, flat spectrum, no crest-factor reduction, the period
        equals :func:`drive_multisine` with the same bins, group, seed and realization.
    """
    if not np.isfinite(fs) or fs <= 0:
        raise InputError(f"multisine: fs must be a positive number of Hz, got {fs}")
    n_period = int(n_period)
    f0 = fs / n_period
    if (f_min is not None or f_max is not None) and (k_min is not None or k_max is not None):
        raise InputError("multisine: give the band either in Hz (f_min, f_max) or in bins "
                         "(k_min, k_max), not both")
    # a band in Hz is clipped to the usable bins 1 .. ceil(N/2) - 1 (no DC, no Nyquist)
    if f_min is not None:
        k_min = max(int(np.ceil(f_min / f0 - 1e-9)), 1)
    if f_max is not None:
        if not np.isfinite(f_max) or f_max > fs / 2 * (1 + 1e-12):
            raise InputError(f"multisine: f_max = {f_max:g} Hz lies above the Nyquist "
                             f"frequency fs/2 = {fs / 2:g} Hz (fs = {fs:g} Hz): no line "
                             f"can be excited there")
        k_max = min(int(np.floor(f_max / f0 + 1e-9)), (n_period - 1) // 2)
    k_min = 1 if k_min is None else int(k_min)
    k_max = (n_period - 1) // 2 if k_max is None else int(k_max)
    _check_band(n_period, k_min, k_max)
    if not np.isfinite(rms) or rms < 0:
        raise InputError(f"multisine: rms must be finite and >= 0, got {rms}")

    if kind == "random_odd":
        lines = drive_lines(n_period, k_min, k_max, group, seed)
    elif kind == "odd":
        lines = drive_lines(n_period, k_min, k_max, 0, seed)
    elif kind == "full":
        lines = _line_set(np.arange(k_min, k_max + 1), [], k_min, k_max)
    else:
        raise InputError(f"multisine: kind must be 'random_odd', 'odd' or 'full', got {kind!r}")
    n_exc = lines.excited.size
    if n_exc == 0:
        raise InputError(f"multisine: no excited line in bins [{k_min}, {k_max}]")

    if amplitude_spectrum is None:
        rel = np.ones(n_exc)
    elif callable(amplitude_spectrum):
        rel = np.asarray(amplitude_spectrum(lines.excited * f0), dtype=float).reshape(-1)
    else:
        rel = np.asarray(amplitude_spectrum, dtype=float).reshape(-1)
    if rel.shape != (n_exc,):
        raise InputError(f"multisine: amplitude_spectrum needs {n_exc} values (one per "
                         f"excited line), got {rel.size}")
    if not np.all(np.isfinite(rel)) or np.any(rel < 0) or not np.any(rel > 0):
        raise InputError("multisine: amplitude_spectrum must be finite, >= 0, not all zero")
    # rms of a sum of sines on distinct bins 0 < k < N/2 is sqrt(sum a^2 / 2)
    amplitudes = rel * (rms / np.sqrt(np.sum(rel ** 2) / 2.0))

    phases = drive_phases(n_exc, seed, realization)
    if crest_factor_iterations:
        phases = _reduce_crest_factor(n_period, lines.excited, amplitudes, phases,
                                      crest_factor_iterations)
    period = synthesize_period(n_period, lines.excited, amplitudes, phases)
    return Multisine(period=period, excited=lines.excited,
                     detection_odd=lines.detection_odd, even=lines.even,
                     removed=lines.removed, phases=phases, amplitudes=amplitudes,
                     fs=float(fs), n_period=n_period, realization=int(realization),
                     seed=int(seed), kind=kind)


def multisine_realizations(n_realizations, fs, n_period, **design):
    """M realizations m = 0 .. M-1 of :func:`design_multisine` (same lines, new phases).

    Returns
    -------
    list of Multisine
        ``np.stack([d.period for d in result])`` is the (M, N) table.
    """
    return [design_multisine(fs, n_period, realization=m, **design)
            for m in range(int(n_realizations))]


def random_odd_multisine(fs, n_period, n_realizations=1, *, f_min=None, f_max=None,
                         k_min=None, k_max=None, group=5, rms=1.0, seed=0):
    """M realizations of a random odd multisine (paper eq. 2), as the drive plays them.

    Odd DFT bins of the band are excited with a flat amplitude spectrum; in each full
    group of ``group`` consecutive odd candidates one line is left out at random (a
    detection line for odd nonlinear distortion, the same for all realizations); even
    bins are never excited. Phases are uniform in [-pi, pi), new for each realization.

    Parameters
    ----------
    fs : float
        Sample rate (Hz).
    n_period : int
        Samples per period N; frequency resolution f0 = fs / N (Hz).
    n_realizations : int
        M, realizations m = 0 .. M-1 (same lines, independent phases).
    f_min, f_max : float, optional
        Band (Hz), inclusive. Or give ``k_min``, ``k_max`` in DFT bins.
    k_min, k_max : int, optional
        Band in DFT bins (default 1 .. N/2 - 1).
    group : int
        Group size G of the random line removal (0: keep every odd line; default 5).
    rms : float
        rms value of each period (signal unit).
    seed : int
        uint32 seed of the line set and the phases (the drive's ``seed`` parameter).

    Returns
    -------
    u : ndarray, shape (M, N)
        One period of each realization (float64).
    design : Multisine
        Realization 0's design: ``excited``, ``detection_odd``, ``even`` bins, phases,
        amplitudes (the line sets are the same for every realization).

    See Also
    --------
    design_multisine : other kinds, user amplitude spectra, crest-factor reduction.

    Examples
    --------
    >>> u, d = random_odd_multisine(1000.0, 1000, 4, f_min=1, f_max=100, rms=0.5)
    >>> u.shape, bool(d.excited.size > 0), bool((d.excited % 2 == 1).all())
    ((4, 1000), True, True)
    """
    designs = multisine_realizations(n_realizations, fs, n_period, f_min=f_min,
                                     f_max=f_max, k_min=k_min, k_max=k_max,
                                     kind="random_odd", group=group, rms=rms, seed=seed)
    if not designs:
        raise InputError(f"multisine: n_realizations must be >= 1, got {n_realizations}")
    return np.stack([d.period for d in designs]), designs[0]
