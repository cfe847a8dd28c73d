"""Figures in the manner of the paper (matplotlib, headless: no pyplot, Agg canvas).

``figureN(...)`` builds and returns a :class:`matplotlib.figure.Figure` (Agg canvas, not
registered with pyplot); ``plot_*(..., path)`` writes it atomically to ``path`` (format
from the suffix, PNG by default) and returns the path.

* :func:`plot_output_spectrum` -- Figure 3: output spectrum with BLA output, nonlinear
  and noise levels, odd and even detection lines.
* :func:`plot_bla_levels` -- Figure 4: BLA vs frequency and excitation level.
  :func:`plot_bla` -- one BLA with its standard deviations.
* :func:`plot_hosidf_amplitude` -- Figure 5: HOSIDFs vs amplitude with std.
  :func:`plot_hosidf_harmonics` -- one experiment's |H_k| and phases.
* :func:`plot_tuning` -- Figure 7: |H_3|, |H_5|, |H_7|, phases and ratio vs K_fc.
* :func:`plot_time_response` -- Figure 9: time response and error for several K_fc.
"""
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from fftune.analysis.errors import InputError

__all__ = ["figure3", "figure4", "figure5", "figure7", "figure9", "figure_bla",
           "figure_hosidf_harmonics", "plot_output_spectrum", "plot_bla", "plot_bla_levels",
           "plot_hosidf_amplitude", "plot_hosidf_harmonics", "plot_tuning",
           "plot_time_response"]


def _figure(rows=1, height=4.0):
    fig = Figure(figsize=(8.0, height * rows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = [fig.add_subplot(rows, 1, i + 1) for i in range(rows)]
    return fig, axes


def _save(fig, path):
    from fftune.analysis.capture import atomic_write

    path = Path(path)
    fmt = path.suffix.lstrip(".") or "png"
    atomic_write(path, lambda tmp: fig.savefig(tmp, format=fmt, dpi=110), overwrite=True,
                 suffix="." + fmt)
    return path


def _db20(x):
    with np.errstate(divide="ignore"):
        return 20 * np.log10(np.abs(x))


def _db10(x):
    if x is None:
        return None
    with np.errstate(divide="ignore", invalid="ignore"):
        return 10 * np.log10(np.where(np.asarray(x) > 0, x, np.nan))


def figure3(result, title=None, unit="unit"):
    """Figure 3: output spectrum of a multisine experiment (returns the Figure).

    Parameters
    ----------
    result : fftune.analysis.bla.BLAResult
    title : str, optional
    unit : str
        Unit of the output signal (levels in dB re 1 ``unit`` amplitude).
    """
    fig, (ax,) = _figure()
    ax.plot(result.freq, result.output_db, "k+", ms=5, label="output at excited lines (BLA)")
    if result.nl_db is not None:
        ax.plot(result.freq, result.nl_db, ".", color="tab:red", ms=4,
                label="nonlinear level (one experiment)")
    if result.noise_db is not None:
        ax.plot(result.freq, result.noise_db, ".", color="tab:green", ms=4, label="noise level")
    if result.odd_bins.size:
        ax.plot(result.odd_freq, result.odd_db, "o", mfc="none", color="tab:red", ms=4,
                label="non-excited odd lines")
    if result.even_bins.size:
        ax.plot(result.even_freq, result.even_db, "^", mfc="none", color="tab:blue", ms=4,
                label="non-excited even lines")
    nonexc = getattr(result, "nonexcited_bins", None)
    if nonexc is not None and nonexc.size and not (result.odd_bins.size or result.even_bins.size):
        ax.plot(nonexc * result.fs / result.n_period, result.nonexcited_db, "s", mfc="none",
                color="tab:purple", ms=3, label=f"non-excited lines (no odd/even split: "
                                                  f"{result.grid} grid)")
    if nonexc is not None and nonexc.size and result.nonexcited_noise_db is not None:
        ax.plot(nonexc * result.fs / result.n_period, result.nonexcited_noise_db, "_",
                color="0.5", ms=4, label="noise at non-excited lines")
    if getattr(result, "plant_db", None) is not None and nonexc.size:
        ax.plot(nonexc * result.fs / result.n_period, result.plant_db, "x", color="tab:orange",
                ms=3, label="plant-referred level at non-excited lines")
    ax.set_xscale("log")
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel(f"amplitude (dB re 1 {unit})")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    ax.set_title(title or "Output spectrum: BLA, nonlinear and noise levels")
    return fig


def plot_output_spectrum(result, path, title=None, unit="unit"):
    """:func:`figure3` written to ``path``; returns the path."""
    return _save(figure3(result, title, unit), path)


def figure_bla(result, title=None):
    """One BLA: magnitude with its total and noise standard deviations, phase."""
    fig, (ax_m, ax_p) = _figure(rows=2, height=3.0)
    ax_m.plot(result.freq, _db20(result.G), "k", label="G_BLA")
    if result.var_total is not None:
        ax_m.plot(result.freq, _db10(result.var_total), "tab:red", lw=0.8,
                  label="std total (s2_BLA)")
    if result.var_noise is not None:
        ax_m.plot(result.freq, _db10(result.var_noise), "tab:green", lw=0.8,
                  label="std noise (s2_BLA,n)")
    ax_m.set_ylabel("dB")
    ax_m.legend(fontsize=7)
    ax_p.plot(result.freq, np.degrees(np.unwrap(np.angle(result.G))), "k")
    ax_p.set_ylabel("phase (deg)")
    for ax in (ax_m, ax_p):
        ax.set_xscale("log")
        ax.grid(True, which="both", alpha=0.3)
    ax_p.set_xlabel("frequency (Hz)")
    ax_m.set_title(title or "Best linear approximation")
    return fig


def plot_bla(result, path, title=None):
    """:func:`figure_bla` written to ``path``."""
    return _save(figure_bla(result, title), path)


def figure4(levels, title=None, g_unit="unit/unit", level_unit="unit"):
    """Figure 4: |G_BLA| vs frequency for each excitation level (colour = rms).

    Parameters
    ----------
    levels : fftune.analysis.bla.BLALevels
    g_unit, level_unit : str
        Unit of the BLA (output per input, e.g. "rad/V") and of the excitation rms.
    """
    from matplotlib import colormaps

    fig, (ax_m, ax_p) = _figure(rows=2, height=3.0)
    cmap = colormaps["viridis"]
    rms = np.asarray(levels.rms)
    span = np.ptp(np.log(rms)) or 1.0
    for i, g in enumerate(levels.G):
        c = cmap(float((np.log(rms[i]) - np.log(rms).min()) / span))
        ax_m.plot(levels.freq, _db20(g), color=c, lw=0.8, label=f"{rms[i]:.3g} {level_unit} rms")
        ax_p.plot(levels.freq, np.degrees(np.unwrap(np.angle(g))), color=c, lw=0.8)
    ax_m.set_ylabel(f"|G_BLA| (dB re 1 {g_unit})")
    ax_p.set_ylabel("phase (deg)")
    ax_p.set_xlabel("frequency (Hz)")
    for ax in (ax_m, ax_p):
        ax.set_xscale("log")
        ax.grid(True, which="both", alpha=0.3)
    ax_m.legend(fontsize=6, ncol=2)
    ax_m.set_title(title or "BLA vs frequency and excitation level")
    return fig


def plot_bla_levels(levels, path, title=None, g_unit="unit/unit", level_unit="unit"):
    """:func:`figure4` written to ``path``."""
    return _save(figure4(levels, title, g_unit, level_unit), path)


def figure5(result, harmonics=(1, 3, 5, 7), frequency_index=0, title=None, unit="unit",
            h_unit="unit/unit"):
    """Figure 5: |H_k| vs the sine's rms amplitude (peak / sqrt 2, as the paper), mean
    (solid) and standard deviation (dashed).

    Parameters
    ----------
    result : fftune.analysis.hosidf.HosidfResult
        Leading axes (L,) amplitudes, or (L, F) amplitudes x frequencies.
    harmonics : sequence of int
    frequency_index : int
        Which frequency when the result is (L, F) (default the first).
    """
    H, std, amp = result.H, result.H_std, np.asarray(result.amplitude)
    if H.ndim == 3:
        H, std, amp = H[:, frequency_index], std[:, frequency_index], amp[:, frequency_index]
    if H.ndim != 2:
        raise InputError(f"plot_hosidf_amplitude: expected H shaped (L, K), got {H.shape}")
    order = np.argsort(amp)
    amp = amp / np.sqrt(2.0)                  # peak -> rms
    fig, (ax_m, ax_p) = _figure(rows=2, height=3.0)
    for k in harmonics:
        if k > H.shape[-1]:
            raise InputError(f"plot_hosidf_amplitude: harmonic {k} not in the result")
        line, = ax_m.plot(amp[order], _db20(H[order, k - 1]), "-", label=f"H_{k}")
        ax_m.plot(amp[order], _db20(std[order, k - 1]), "--", color=line.get_color(), lw=0.8)
        ax_p.plot(amp[order], np.degrees(np.angle(H[order, k - 1])), "-", color=line.get_color())
    ax_m.set_ylabel(f"|H_k| (dB re 1 {h_unit})")
    ax_p.set_ylabel("phase (deg)")
    ax_p.set_xlabel(f"sine amplitude ({unit} rms)")
    for ax in (ax_m, ax_p):
        ax.set_xscale("log")
        ax.grid(True, which="both", alpha=0.3)
    ax_m.legend(fontsize=7)
    f0 = np.asarray(result.f0).reshape(-1)[0]
    if np.ndim(result.f0) == 2:
        f0 = np.asarray(result.f0)[0, frequency_index]
    ax_m.set_title(title or f"HOSIDFs at {f0:g} Hz: mean (-) and std (--)")
    return fig


def plot_hosidf_amplitude(result, path, harmonics=(1, 3, 5, 7), frequency_index=0,
                          title=None, unit="unit", h_unit="unit/unit"):
    """:func:`figure5` written to ``path``."""
    return _save(figure5(result, harmonics, frequency_index, title, unit, h_unit), path)


def figure_hosidf_harmonics(result, title=None):
    """One experiment: |H_k| (dB re H_1) with std, and phase, per harmonic k."""
    H = np.asarray(result.H).reshape(-1, len(result.harmonics))[0]
    std = np.asarray(result.H_std).reshape(-1, len(result.harmonics))[0]
    k = result.harmonics
    fig, (ax_m, ax_p) = _figure(rows=2, height=3.0)
    ref = np.abs(H[0])
    rel_db = _db20(H / ref)
    ax_m.plot(k, np.where(np.isfinite(rel_db), rel_db, np.nan), "o-", label="|H_k| / |H_1|")
    if np.all(np.isfinite(std)):
        ax_m.plot(k, _db20(std / ref), "k_", ms=14, label="std")
    ax_m.set_ylabel("dB re |H_1|")
    ax_m.legend(fontsize=7)
    ax_p.plot(k, np.degrees(np.angle(H)), "o")
    ax_p.set_ylabel("phase (deg)")
    ax_p.set_xlabel("harmonic k")
    for ax in (ax_m, ax_p):
        ax.set_xticks(k)
        ax.grid(True, alpha=0.3)
    f0 = float(np.asarray(result.f0).reshape(-1)[0])
    ax_m.set_title(title or f"HOSIDF at f0 = {f0:g} Hz")
    return fig


def plot_hosidf_harmonics(result, path, title=None):
    """:func:`figure_hosidf_harmonics` written to ``path``."""
    return _save(figure_hosidf_harmonics(result, title), path)


def figure7(k_fc, H, ratio=None, *, k_star=None, harmonics=(3, 5, 7), H_std=None,
            title=None):
    """Figure 7: |H_i| and phases of the odd HOSIDFs and their ratio to H_1 vs K_fc.

    Parameters
    ----------
    k_fc : array_like, shape (n,)
        Feed-forward gains of the experiments.
    H : array_like of complex, shape (n, K)
        HOSIDFs at each K_fc.
    ratio : array_like, shape (n,), optional
        The objective r per experiment; computed with
        :func:`fftune.analysis.tuning.odd_ratio` if omitted.
    k_star : float, optional
        K_fc* to mark.
    harmonics : sequence of int
    H_std : array_like, shape (n, K), optional
        Standard deviations (plotted as dots).
    """
    from fftune.analysis.tuning import odd_ratio

    k_fc = np.asarray(k_fc, dtype=float)
    H = np.asarray(H)
    if H.ndim != 2 or H.shape[0] != k_fc.size:
        raise InputError(f"plot_tuning: H must be shaped (len(k_fc), K), got {H.shape}")
    order = np.argsort(k_fc)
    k_fc, H = k_fc[order], H[order]
    fig, (ax_m, ax_p, ax_r) = _figure(rows=3, height=2.6)
    for k in harmonics:
        line, = ax_m.plot(k_fc, np.abs(H[:, k - 1]), "-o", ms=3, label=f"|H_{k}|")
        if H_std is not None:
            ax_m.plot(k_fc, np.asarray(H_std)[order, k - 1], ".", color=line.get_color())
        ax_p.plot(k_fc, np.degrees(np.angle(H[:, k - 1])), "-o", ms=3, color=line.get_color())
    ratio = odd_ratio(H, harmonics) if ratio is None else np.asarray(ratio, dtype=float)[order]
    ax_r.plot(k_fc, 100 * ratio, "k-o", ms=3)
    ax_m.set_ylabel("|H_k| (rad/rad)")
    ax_p.set_ylabel("phase (deg)")
    ax_r.set_ylabel("odd NL / linear (%)")
    ax_r.set_xlabel("K_fc (V)")
    ax_m.legend(fontsize=7)
    for ax in (ax_m, ax_p, ax_r):
        ax.grid(True, alpha=0.3)
        if k_star is not None:
            ax.axvline(k_star, color="tab:red", lw=0.8, ls="--")
    ax_m.set_title(title or "Odd HOSIDFs vs Coulomb feed forward K_fc")
    return fig


def plot_tuning(k_fc, H, path, ratio=None, *, k_star=None, harmonics=(3, 5, 7), H_std=None,
                title=None):
    """:func:`figure7` written to ``path``."""
    return _save(figure7(k_fc, H, ratio, k_star=k_star, harmonics=harmonics, H_std=H_std,
                         title=title), path)


def figure9(fs, reference, outputs, errors=None, title=None):
    """Figure 9: time responses and tracking errors for several K_fc.

    Parameters
    ----------
    fs : float
        Sample rate (Hz); time axis t = n / fs.
    reference : array_like, shape (n,)
    outputs : dict of str -> array_like (n,)
        Label (e.g. "K_fc = 0.1157") -> measured output.
    errors : dict of str -> array_like (n,), optional
        Measured tracking errors with the same labels; reference - output if omitted.
    """
    reference = np.asarray(reference, dtype=float).reshape(-1)
    t = np.arange(reference.size) / float(fs)
    fig, (ax_y, ax_e) = _figure(rows=2, height=3.0)
    ax_y.plot(t, reference, "k--", lw=1, label="reference")
    for label, y in outputs.items():
        y = np.asarray(y, dtype=float).reshape(-1)
        if y.shape != t.shape:
            raise InputError(f"figure9: output {label!r} has {y.size} samples, the reference "
                             f"{t.size}")
        err = reference - y if errors is None else np.asarray(errors[label], dtype=float)
        if err.shape != t.shape:
            raise InputError(f"figure9: error {label!r} has {err.size} samples, expected {t.size}")
        ax_y.plot(t, y, lw=1, label=label)
        ax_e.plot(t, err, lw=1, label=f"{label} (rms {np.sqrt(np.mean(err ** 2)):.3g} rad)")
    ax_y.set_ylabel("motor angle (rad)")
    ax_e.set_ylabel("tracking error (rad)")
    ax_e.set_xlabel("time (s)")
    for ax in (ax_y, ax_e):
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    ax_y.set_title(title or "Closed-loop response for several K_fc")
    return fig


def plot_time_response(fs, reference, outputs, path, errors=None, title=None):
    """:func:`figure9` written to ``path``."""
    return _save(figure9(fs, reference, outputs, errors, title), path)
