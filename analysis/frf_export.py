"""A measured FRF (the BLA) with its variances as a MATLAB ``.mat`` file.

:func:`frf_mat_content` lays one FRF out for three readers at once (one file, no
conversion on the MATLAB side):

* MATLAB's ``frd`` / ``idfrd`` (Control System and System Identification toolboxes) and
  GNU Octave's control package ``frd``:
  ``ResponseData`` (ny x nu x F = 1 x 1 x F, complex), ``Frequency`` (F x 1, rad/s),
  ``Ts`` (0: a continuous-time FRF), ``CovarianceData`` (1 x 1 x F x 2 x 2: the covariance
  of the real and imaginary parts, idfrd's layout; the estimate's error taken circular:
  each part var/2, uncorrelated)::

      d = load('bla-L01.mat');
      sys = idfrd(d.ResponseData, d.Frequency, d.Ts, 'CovarianceData', d.CovarianceData);
      sys = frd(d.ResponseData, d.Frequency);          % Control System Toolbox / Octave

* FdiTools (T. Beauduin, KU Leuven: ``time2bla``, ``mlfdi``, ``nlsfdi``): ``freq`` (F x 1,
  Hz), the FRF as input/output spectra ``X`` = 1 and ``Y`` = G (F x 1), their variances
  per real/imaginary part ``sX2`` = 0, ``sY2`` = var/2 and covariance ``cXY`` = 0 (F x 1),
  and ``Gbla`` (4 x F, as ``time2bla`` returns it: mean, total std, noise std, std of the
  stochastic nonlinear distortions)::

      [Hml, Hls] = mlfdi(d.X, d.Y, d.freq, d.sX2, d.sY2, d.cXY, n, mh, ml, 20, 1e-6, 0, 'c', d.fs);

* anyone: ``G``, ``varG`` (total variance s2_BLA), ``varG_noise``, ``varG_nl`` (F x 1),
  ``fs``, ``n_period``, ``input_unit``, ``output_unit``, ``description``.

Every number is a double; the file is written atomically (:func:`scipy.io.savemat`, v5).
"""
import numpy as np

from fftune.analysis.errors import InputError

__all__ = ["frf_mat_content", "export_frf_mat", "export_bla_mat"]

LAYOUT = ("MATLAB frd/idfrd (ResponseData 1x1xF, Frequency rad/s, CovarianceData 1x1xFx2x2), "
          "FdiTools mlfdi/nlsfdi/time2bla (freq Hz, X, Y, sX2, sY2, cXY, Gbla 4xF), plain G/varG")


def _column(name, x, n, dtype=float):
    a = np.asarray(x, dtype=dtype).reshape(-1)
    if a.size != n:
        raise InputError(f"frf_mat_content: {name} has {a.size} values, the FRF {n}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"frf_mat_content: {name} holds a non-finite value")
    return a


def frf_mat_content(freq_hz, G, var_total=None, var_noise=None, var_nl=None, *, fs=None,
                    n_period=None, input_unit="", output_unit="", description=""):
    """The ``.mat`` variables of one SISO FRF and its variances (dict name -> array).

    Parameters
    ----------
    freq_hz : array_like, shape (F,)
        Frequencies (Hz), increasing, positive.
    G : array_like of complex, shape (F,)
    var_total, var_noise, var_nl : array_like, shape (F,), optional
        Variance of G (E|G_est - G|^2: s2_BLA, its noise part s2_BLA,n, and s2_S of one
        experiment's stochastic nonlinear distortions; docs/method.md). Without
        ``var_total`` there is no CovarianceData and sY2 is zero.
    fs : float, optional
        Sample rate of the measurement (Hz).
    """
    f = np.asarray(freq_hz, dtype=float).reshape(-1)
    F = f.size
    if F == 0:
        raise InputError("frf_mat_content: no frequencies")
    if not np.all(np.isfinite(f)) or np.any(f <= 0) or np.any(np.diff(f) <= 0):
        raise InputError("frf_mat_content: frequencies must be positive and increasing (Hz)")
    g = _column("G", G, F, complex)
    v = None if var_total is None else _column("var_total", var_total, F)
    if v is not None and np.any(v < 0):
        raise InputError("frf_mat_content: var_total must be >= 0")
    vn = None if var_noise is None else _column("var_noise", var_noise, F)
    vnl = None if var_nl is None else _column("var_nl", var_nl, F)
    col = lambda a: np.asarray(a).reshape(F, 1)  # noqa: E731
    zeros = np.zeros((F, 1))
    out = {
        "freq": col(f), "G": col(g),
        "ResponseData": g.reshape(1, 1, F), "Frequency": col(2 * np.pi * f),
        "FrequencyUnit": "rad/s", "Ts": 0.0,
        "X": np.ones((F, 1), dtype=complex), "Y": col(g), "sX2": zeros, "cXY": zeros,
        "sY2": col(v / 2.0) if v is not None else zeros,
        "input_unit": str(input_unit), "output_unit": str(output_unit),
        "description": str(description), "layout": LAYOUT,
    }
    if v is not None:
        cov = np.zeros((1, 1, F, 2, 2))
        cov[0, 0, :, 0, 0] = cov[0, 0, :, 1, 1] = v / 2.0
        out["CovarianceData"] = cov
        out["varG"] = col(v)
    if vn is not None:
        out["varG_noise"] = col(vn)
    if vnl is not None:
        out["varG_nl"] = col(vnl)
    gbla = np.zeros((4, F), dtype=complex)
    gbla[0] = g
    gbla[1] = np.sqrt(v) if v is not None else np.nan
    gbla[2] = np.sqrt(vn) if vn is not None else np.nan
    gbla[3] = np.sqrt(np.maximum(vnl, 0.0)) if vnl is not None else np.nan
    out["Gbla"] = gbla
    if fs is not None:
        out["fs"] = float(fs)
    if n_period is not None:
        out["n_period"] = float(n_period)
    return out


def export_frf_mat(path, content, *, overwrite=False):
    """``content`` (:func:`frf_mat_content`) written to ``path`` atomically (v5 .mat)."""
    import scipy.io

    from fftune.analysis.capture import atomic_write
    return atomic_write(path, lambda tmp: scipy.io.savemat(tmp, content, format="5",
                                                           do_compression=True),
                        overwrite=overwrite, suffix=".mat")


def export_bla_mat(result, path, *, overwrite=False, input_unit="", output_unit="",
                   description=""):
    """A :class:`fftune.analysis.bla.BLAResult` as ``.mat`` (:func:`frf_mat_content`'s
    layout): G_BLA at the excited lines with ``var_total``, ``var_noise``, ``var_nl``."""
    content = frf_mat_content(result.freq, result.G, result.var_total, result.var_noise,
                              result.var_nl, fs=result.fs, n_period=result.n_period,
                              input_unit=input_unit, output_unit=output_unit,
                              description=description or "best linear approximation (fftune)")
    return export_frf_mat(path, content, overwrite=overwrite)
