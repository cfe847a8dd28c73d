"""The closed loop's sensitivity measured from a periodic excitation's records.

With the excitation ``d`` added to the controller's output (``detect.inject:
plant_input``) the plant input is ``u = d - C y`` and ``U/D = 1 / (1 + C G) = S_i``, the
input sensitivity; with the excitation as the position reference (``inject: reference``)
the tracking error ``e = r - y`` gives ``E/R = S``, the output sensitivity. For a linear
loop both are the same function; with friction in the loop it depends on the level (the
BLA of the loop). The peak of ``|S|`` (M_s) is the loop's robustness margin: the distance
of the Nyquist curve from -1 is 1/M_s.
"""
import numpy as np

from fftune.analysis.errors import InputError

__all__ = ["sensitivity"]


def sensitivity(x, d, *, fs, rel_floor=1e-3):
    """The sensitivity ``X/D`` at the excited lines of a periodic excitation.

    Parameters
    ----------
    x : array_like (M, P, N)
        The loop's response to the excitation over M realizations and P whole periods of
        N samples: the plant input (excitation at the plant input) or the tracking error
        ``r - y`` (excitation as the reference).
    d : array_like (M, P, N) or (M, N)
        The excitation (the same every period).
    fs : float
        Sample rate (Hz).
    rel_floor : float
        A line is excited where the realization's mean ``|D|`` exceeds ``rel_floor`` times
        its largest line.

    Returns
    -------
    freq : ndarray (K,)
        The lines excited in every realization (Hz).
    S : ndarray (K,) complex
        Mean over the realizations of the period-averaged ``X/D``.
    var : ndarray (K,)
        Its variance (the spread over the realizations / M; NaN for M = 1).
    """
    x = np.asarray(x, dtype=float)
    d = np.asarray(d, dtype=float)
    if x.ndim != 3:
        raise InputError(f"sensitivity: x must be (M, P, N), got shape {x.shape}")
    if d.ndim == 2:
        d = d[:, None, :]
    if d.ndim != 3 or d.shape[0] != x.shape[0] or d.shape[2] != x.shape[2]:
        raise InputError(f"sensitivity: d of shape {d.shape} does not match x {x.shape}")
    if not fs > 0:
        raise InputError(f"sensitivity: fs must be > 0, got {fs}")
    m, _, n = x.shape
    X = np.fft.rfft(x, axis=-1).mean(axis=1)[:, 1:]
    D = np.fft.rfft(d, axis=-1).mean(axis=1)[:, 1:]
    mag = np.abs(D)
    excited = np.all(mag > rel_floor * mag.max(axis=1, keepdims=True), axis=0)
    if not excited.any():
        raise InputError("sensitivity: no line is excited in every realization")
    ratio = X[:, excited] / D[:, excited]
    S = ratio.mean(axis=0)
    var = (np.sum(np.abs(ratio - S) ** 2, axis=0) / (m - 1) / m) if m > 1 else np.full(S.shape, np.nan)
    freq = (np.flatnonzero(excited) + 1) * float(fs) / n
    return freq, S, var
