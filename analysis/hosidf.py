"""Higher Order Sinusoidal Input Describing Functions (HOSIDF) from sine experiments.

For an input w(t) = beta sin(2 pi f0 t) and output y (paper eq. 4-5):

    |H_k| = |Y(k f0)| / |U(f0)|,    angle H_k = angle Y(k f0) - k angle U(f0),

i.e. H_k = Y(k f0) exp(-j k angle U(f0)) / |U(f0)|, k = 1 .. K, from the DFT over an
integer number of periods of the sine (leakage free). Repeated experiments give the mean
and the standard deviation of H_k.

Data layout: arrays shaped ``(..., R, P, N)``: any leading axes (e.g. amplitude x
frequency), R repeats, P blocks of N samples. Each block holds an integer number of sine
periods, so the P blocks are averaged in the time domain before one DFT of N samples
(identical to the DFT of the whole record at the harmonic bins, and P times cheaper).
A single record is ``x.reshape(1, 1, -1)``.
"""
from dataclasses import dataclass, field

import numpy as np

from fftune.analysis.checks import check_arguments, check_blocks
from fftune.analysis.errors import InputError

__all__ = ["HosidfResult", "hosidf", "hosidf_from_lines"]


@dataclass
class HosidfResult:
    """HOSIDFs of a set of sine experiments.

    Attributes
    ----------
    harmonics : ndarray of int, shape (K,)
        k = 1 .. K.
    f0 : ndarray, shape (...)
        Sine frequency (Hz) of each experiment.
    bin : ndarray of int, shape (...)
        Its DFT bin in a block of N samples.
    amplitude : ndarray, shape (...)
        Sine amplitude beta (input unit, peak), mean over repeats.
    H : ndarray of complex, shape (..., K)
        Mean over repeats of H_k (output unit / input unit).
    H_std : ndarray, shape (..., K)
        Standard deviation over repeats of the complex H_k,
        sqrt(sum_r |H_k,r - H_k|^2 / (R - 1)); NaN when R = 1.
    H_repeats : ndarray of complex, shape (..., R, K)
        H_k of every repeat.
    fs : float
        Sample rate (Hz).
    notes : list of str
        What the checks before averaging handled (blocks without excitation dropped ...).
    """

    harmonics: np.ndarray
    f0: np.ndarray
    bin: np.ndarray
    amplitude: np.ndarray
    H: np.ndarray
    H_std: np.ndarray
    H_repeats: np.ndarray
    fs: float
    notes: list = field(default_factory=list)

    @property
    def magnitude(self):
        """|H_k| of the mean, shape (..., K)."""
        return np.abs(self.H)

    @property
    def phase_deg(self):
        """angle H_k of the mean in degrees, shape (..., K)."""
        return np.degrees(np.angle(self.H))


def _check_layout(name, x):
    x = np.asarray(x)
    if x.ndim < 3:
        raise InputError(f"{name}: expected an array shaped (..., repeats R, blocks P, "
                         f"samples N), got shape {x.shape}")
    if not (np.issubdtype(x.dtype, np.floating) or np.issubdtype(x.dtype, np.integer)):
        raise InputError(f"{name}: expected real numbers, got dtype {x.dtype}")
    return x


def hosidf(u, y, *, fs=1.0, n_harmonics=7, f0=None, leakage_tol=1e-2, other_line_tol=0.1):
    """HOSIDFs H_1 .. H_K from sine experiments, mean and std over repeats.

    Parameters
    ----------
    u, y : array_like, shape (..., R, P, N)
        Input (the sine) and output; R repeats of P blocks of N samples, each block an
        integer number of sine periods, in steady state.
    fs : float
        Sample rate (Hz).
    n_harmonics : int
        K, the highest harmonic (K f0 must stay below fs / 2).
    f0 : float or array_like, optional
        Sine frequency (Hz), broadcast over the leading axes. Checked to lie on a DFT
        line of the N-sample block. Found from the input spectrum if omitted.
    leakage_tol : float
        When f0 is found from the data: a record whose largest input line has both
        neighbours above ``leakage_tol`` times its magnitude is rejected as a sine off
        the DFT grid (a sine off by d bins raises them to about d / (1 -+ d)). Not
        checked for a sine of one period per block (its neighbours are DC and the
        second harmonic): give ``f0`` there.
    other_line_tol : float
        The input must be one sine: a record with another input line (not a harmonic of
        f0) above ``other_line_tol`` times the sine's magnitude, or a harmonic of f0 above
        half of it, is rejected (a multisine is not a sine: its other excited lines
        would be read as harmonics of the lowest one).

    Returns
    -------
    HosidfResult

    Raises
    ------
    InputError
        Bad layout, NaN/inf, zero input, an input that is not one sine, sine off the DFT
        grid, repeats at different frequencies, harmonics beyond Nyquist.
    """
    u = _check_layout("input u", u)
    y = _check_layout("output y", y)
    if u.shape != y.shape:
        raise InputError(f"output y: shape {y.shape} differs from input u {u.shape}")
    fs, _ = check_arguments(fs=fs)
    n_harmonics = int(n_harmonics)
    if n_harmonics < 1:
        raise InputError(f"harmonics K must be >= 1, got {n_harmonics}")
    # every block of every repeat carries the same sine at one level (checked before the
    # blocks are averaged): a burst's empty blocks are dropped, the rest is refused
    notes = []
    if u.ndim == 3:
        layout = check_blocks(u, kind="sine", name="input u", group="repeat", block="block",
                              fs=fs)
        if layout.changed:
            u, y = layout.apply(u), layout.apply(y)
            notes = list(layout.notes)
    else:
        for idx in np.ndindex(u.shape[:-3]):
            layout = check_blocks(u[idx], kind="sine", name=f"input u (experiment {idx})",
                                  group="repeat", block="block", fs=fs)
            if layout.changed:
                raise InputError(f"{layout.notes[0]}; give this experiment on its own "
                                 f"(its blocks differ from the others' layout)")
    n = u.shape[-1]
    n_blocks = u.shape[-2]
    n_lines = n // 2 + 1
    # periods averaged in the time domain (exact at the sine's harmonics), then one rfft
    import scipy.fft  # here: `import fftune.analysis` (the CLI's start) stays free of scipy

    U = scipy.fft.rfft(u.sum(axis=-2), axis=-1)
    if not np.isfinite(U).all():
        from fftune.analysis.checks import locate_nonfinite
        raise InputError(locate_nonfinite("input u", np.reshape(u, (-1,) + u.shape[-2:]),
                                          group="repeat", block="block")
                         or "input u: contains NaN or inf")
    lead = U.shape[:-1]                       # (..., R)

    if f0 is None:
        mag = np.abs(U[..., 1:n_lines - 1])
        if mag.shape[-1] == 0:
            raise InputError(f"input u: N = {n} samples per block is too short")
        k0 = np.argmax(mag, axis=-1) + 1
        peak = np.take_along_axis(np.abs(U), k0[..., None], axis=-1)[..., 0]
        if np.any(peak == 0):
            raise InputError("input u: zero input (no sine found)")
        left = np.take_along_axis(np.abs(U), (k0 - 1)[..., None], axis=-1)[..., 0]
        right = np.take_along_axis(np.abs(U), np.minimum(k0 + 1, n_lines - 1)[..., None],
                                   axis=-1)[..., 0]
        # an off-grid sine raises both neighbours (d/(1-d), d/(1+d)): the smaller one is
        # the test, so that a harmonic of the input next to the peak does not count.
        # For k0 = 1 the neighbours are DC and the 2nd harmonic: no test (give f0).
        leak = np.where(k0 > 1, np.minimum(left, right) / peak, 0.0)
        bad = np.argwhere(leak > leakage_tol)
        if bad.size:
            idx = tuple(int(i) for i in bad[0])
            _check_envelope(u[idx], idx, fs)
            raise InputError(
                f"input u: record {idx} has its sine off the DFT grid (neighbouring lines at "
                f"{leak[idx]:.2g} of the peak near {k0[idx] * fs / n:g} Hz): record an integer "
                f"number of sine periods per block of N = {n} samples")
    else:
        f0_arr = np.broadcast_to(np.asarray(f0, dtype=float)[..., None], lead)
        exact = f0_arr * n / fs
        k0 = np.rint(exact).astype(np.int64)
        off = np.abs(exact - k0)
        if np.any(off > 1e-6 * np.maximum(exact, 1.0)) or np.any(k0 < 1):
            idx = tuple(int(i) for i in np.argwhere(
                (off > 1e-6 * np.maximum(exact, 1.0)) | (k0 < 1))[0])
            raise InputError(
                f"input u: the sine at {f0_arr[idx]:g} Hz (record {idx}) is not on a DFT "
                f"line: f0 N / fs = {exact[idx]:.6g} is not an integer (N = {n}, fs = {fs:g} Hz)")
    _check_one_sine(np.abs(U), k0, other_line_tol, fs, n)
    if k0.ndim and np.any(k0 != k0[..., :1]):
        raise InputError("input u: the repeats of one experiment have sines at different "
                         "frequencies")
    if np.any(k0 * n_harmonics >= n / 2):
        worst = int(k0.max())
        raise InputError(f"harmonic K = {n_harmonics} of the sine at {worst * fs / n:g} Hz lies "
                         f"at or above fs/2 = {fs / 2:g} Hz: ask for fewer harmonics K")

    U1 = np.take_along_axis(U, k0[..., None], axis=-1)[..., 0]
    del U
    Y = scipy.fft.rfft(y.sum(axis=-2), axis=-1)
    Yk = np.take_along_axis(Y, k0[..., None] * np.arange(1, n_harmonics + 1), axis=-1)
    del Y
    if not np.isfinite(Yk).all():
        from fftune.analysis.checks import locate_nonfinite
        text = locate_nonfinite("output y", np.reshape(y, (-1,) + y.shape[-2:]),
                                group="repeat", block="block")
        if text:
            raise InputError(text)
    if u.ndim == 3 and n_blocks >= 4:
        Yk = _without_drift(u, y, Yk, int(k0.reshape(-1)[0]), n_harmonics, notes)
    res = hosidf_from_lines(U1, Yk, k0[..., 0], n=n, n_blocks=n_blocks, fs=fs)
    res.notes.extend(notes)
    return res


def _without_drift(u, y, Yk, k0, n_harmonics, notes):
    """An output that drifts over the blocks (its DC per block has a trend, t > 6): the
    drift's leakage at the harmonics is the same in every block, so averaging keeps it;
    the local polynomial method (:mod:`fftune.analysis.lpm`) removes it from the lines
    k0 .. K k0 of the whole record. Returns the corrected block sums (else ``Yk``)."""
    from fftune.analysis.bla import _drift_test

    drift = _drift_test(np.add.reduce(y, axis=-1, dtype=np.float64))
    if drift is None:
        return Yk
    from fftune.analysis.lpm import lpm_moments

    harmonics = k0 * np.arange(1, n_harmonics + 1)
    band = np.arange(k0, harmonics[-1] + 1)
    mom, _, info = lpm_moments(np.asarray(u, dtype=np.float64), np.asarray(y, dtype=np.float64),
                               band=band, excited=harmonics)
    if not info.significant:
        notes.append(f"the output drifts (its DC moves {drift[1]:+.3g} per block in repeat "
                     f"{drift[0]}, t = {drift[2]:+.1f}), but the local polynomial method finds "
                     f"it under the noise at the harmonics: plain averaging kept")
        return Yk
    notes.append(f"drift of the output (its DC moves {drift[1]:+.3g} per block in repeat "
                 f"{drift[0]}, t = {drift[2]:+.1f}) removed at the harmonics by the local "
                 f"polynomial method: {info.transient_re_output_db:.1f} dB re the output "
                 f"there, median {info.transient_re_noise_db:+.1f} dB re its standard error")
    return mom.Y[:, harmonics - k0] * u.shape[-2]


def _check_envelope(blocks, idx, fs, segments=32):
    """Before calling a record's sine "off the grid": an excitation that stops or pauses
    inside the record (a burst) leaks as well. InputError naming the sample where the
    envelope (rms over 1/32 of a block) falls 20 dB under its median, if it does."""
    x = np.asarray(blocks, dtype=np.float64).reshape(-1)
    seg = max(x.size // (segments * blocks.shape[0]), 1)
    m = x.size // seg
    env = np.sqrt(np.mean(x[:m * seg].reshape(m, seg) ** 2, axis=1))
    med = float(np.median(env))
    low = np.flatnonzero(env < 0.1 * med)
    if not low.size or not med > 0:
        return
    amp = float(np.median(np.max(np.abs(x[:m * seg].reshape(m, seg)), axis=1)))
    if low[-1] == m - 1 and np.all(np.diff(low) == 1):
        above = np.flatnonzero(np.abs(x) > 0.3 * amp)
        stop = int(above[-1]) + 1 if above.size else 0
        raise InputError(f"input u: record {idx}: the excitation stops at sample {stop} "
                         f"({stop / fs:.4g} s) of {x.size}, before the record ends (a burst): "
                         f"cut the record to the excitation (whole sine periods), or give it "
                         f"as blocks of whole periods (the blocks without excitation are "
                         f"then dropped)")
    start = int(low[0]) * seg
    raise InputError(f"input u: record {idx}: the excitation pauses or starts late (20 dB "
                     f"under its median level from sample {start} ({start / fs:.4g} s)): cut "
                     f"the record to the part with the sine")


def _check_one_sine(mag, k0, tol, fs, n):
    """InputError unless each record's input is one sine at bin k0: every other line
    (DC and the Nyquist line excepted) stays under ``tol`` of the sine's magnitude, its
    harmonics under 0.5 (a distorted sine is still a sine)."""
    lines = mag[..., 1:n // 2]                    # bins 1 .. N/2 - 1
    k = np.arange(1, lines.shape[-1] + 1)
    peak = np.take_along_axis(mag, k0[..., None], axis=-1)
    rel = lines / np.where(peak > 0, peak, np.inf)
    harmonic = (k % k0[..., None]) == 0
    limit = np.where(harmonic, 0.5, tol)
    limit = np.where(k == k0[..., None], np.inf, limit)
    bad = rel > limit
    if not bad.any():
        return
    idx = tuple(int(i) for i in np.argwhere(bad.any(axis=-1))[0])
    worst = int(np.argmax(np.where(bad[idx], rel[idx], 0.0)))
    count = int(bad[idx].sum())
    raise InputError(
        f"input u: not one sine: record {idx} has {count} other input line(s) comparable to "
        f"the one at {k0[idx] * fs / n:g} Hz (the largest at {k[worst] * fs / n:g} Hz, "
        f"{20 * np.log10(rel[idx][worst]):+.1f} dB re it; allowed "
        f"{20 * np.log10(tol):.0f} dB): the HOSIDF needs a single-sine input (a multisine "
        f"record is analysed with the BLA)")


def hosidf_from_lines(U1, Yk, bins, *, n, n_blocks, fs):
    """HOSIDFs from the DFT lines of sine experiments (the last step of :func:`hosidf`;
    :mod:`fftune.analysis.stats` calls it with the drive's on-board line statistics).

    Parameters
    ----------
    U1 : array_like of complex, shape (..., R)
        Input DFT at the sine's bin, summed over the P blocks of N samples (any common
        scale of U1 and Yk gives the same H; ``amplitude`` uses this one).
    Yk : array_like of complex, shape (..., R, K)
        Output DFT at the bins k x bin, k = 1 .. K, summed the same way.
    bins : array_like of int, shape (...)
        The sine's bin in a block of N samples.
    n, n_blocks : int
        N and P.
    fs : float
        Sample rate (Hz).

    Returns
    -------
    HosidfResult
    """
    U1 = np.asarray(U1, dtype=complex)
    Yk = np.asarray(Yk, dtype=complex)
    if np.any(U1 == 0) or not np.isfinite(U1).all():
        raise InputError("input u: zero power at the sine frequency")
    if not np.isfinite(Yk).all():
        raise InputError("output y: contains NaN or inf")
    harmonics = np.arange(1, Yk.shape[-1] + 1)
    H_rep = Yk * np.exp(-1j * harmonics * np.angle(U1)[..., None]) / np.abs(U1)[..., None]
    H = H_rep.mean(axis=-2)
    n_rep = H_rep.shape[-2]
    if n_rep > 1:
        d = H_rep - H[..., None, :]
        H_std = np.sqrt(np.sum(d.real ** 2 + d.imag ** 2, axis=-2) / (n_rep - 1))
    else:
        H_std = np.full(H.shape, np.nan)
    amplitude = (2.0 * np.abs(U1) / (n * n_blocks)).mean(axis=-1)
    bins = np.asarray(bins)
    return HosidfResult(harmonics=harmonics, f0=bins * fs / n, bin=bins, amplitude=amplitude,
                        H=H, H_std=H_std, H_repeats=H_rep, fs=float(fs))
