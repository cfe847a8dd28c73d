"""Figures in the manner of the paper (matplotlib, headless: no pyplot, Agg canvas).

``figureN(...)`` builds and returns a :class:`matplotlib.figure.Figure` (Agg canvas, not
registered with pyplot); ``plot_*(..., path)`` writes it atomically to ``path`` (format
from the suffix, PNG by default) and returns the path.

* :func:`plot_output_spectrum` -- Figure 3: output spectrum with BLA output, nonlinear
  and noise levels, odd and even detection lines.
* :func:`plot_bla_levels` -- Figure 4: BLA vs frequency and excitation level.
  :func:`plot_bla` -- one BLA with its standard deviations (and confidence band).
* :func:`figure_error_spectrum` -- tracking-error spectra (the loop without / with
  feed-forward).
* :func:`figure_sensitivity` -- the measured sensitivity |S| of the loop (its peak M_s).
* :func:`legend_outside_data` -- the rule every figure keeps: no legend over an axes.
* :func:`plot_hosidf_amplitude` -- Figure 5: HOSIDFs vs amplitude with std.
  :func:`plot_hosidf_harmonics` -- one experiment's |H_k| and phases.
* :func:`plot_tuning` -- Figure 7: |H_3|, |H_5|, |H_7|, unwrapped phases and ratio (%) vs K_fc.
  :func:`figure8` -- Figure 8 style: the same with standard deviations and the even level.
* :func:`plot_time_response` -- Figure 9: time response and error for several K_fc.
"""
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from fftune.analysis.errors import InputError

__all__ = ["figure3", "figure4", "figure5", "figure7", "figure8", "figure9", "figure_bla",
           "figure_error_spectrum", "figure_sensitivity", "legend_outside_data",
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


def _legend_outside(ax, **kw):
    """The legend of ``ax`` to the right of its data area (never over the data): anchored
    at the axes' top-right corner, outside it; the constrained layout makes room."""
    kw.setdefault("fontsize", 8)
    return ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, **kw)


def legend_outside_data(fig):
    """The legends of ``fig`` that overlap an axes' data area or its axis labels (display
    boxes after a draw):
    a list of (axes title or index, legend) pairs, empty when every legend is outside.
    The report's rule: a legend never covers data (tests check every figure with it)."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    bad = []
    legends = [(ax, ax.get_legend()) for ax in fig.axes] + [(None, lg) for lg in fig.legends]
    for owner, lg in legends:
        if lg is None:
            continue
        box = lg.get_window_extent(renderer)
        for i, ax in enumerate(fig.axes):
            # the data area and the axis labels (a legend under the axes must clear its
            # x label)
            for a in [ax.get_window_extent(renderer)] + [
                    lab.get_window_extent(renderer) for lab in (ax.xaxis.label, ax.yaxis.label)
                    if lab.get_text() and lab.get_visible()]:
                if box.x0 < a.x1 - 0.5 and box.x1 > a.x0 + 0.5 and box.y0 < a.y1 - 0.5 and box.y1 > a.y0 + 0.5:
                    bad.append((ax.get_title() or i, lg))
                    break
    return bad


def _plain_log_axis(ax, axis="x"):
    """Log scale with plain tick labels (20, 50, 0.3), not 2x10^1."""
    from matplotlib.ticker import FuncFormatter, LogLocator

    fmt = FuncFormatter(lambda v, _pos: f"{v:g}")
    target = ax.xaxis if axis == "x" else ax.yaxis
    (ax.set_xscale if axis == "x" else ax.set_yscale)("log")
    target.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
    target.set_major_formatter(fmt)
    target.set_minor_formatter(FuncFormatter(lambda v, _pos: ""))


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
    _plain_log_axis(ax)
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel(f"amplitude (dB re 1 {unit})")
    ax.grid(True, which="both", alpha=0.3)
    _legend_outside(ax)
    ax.set_title(title or "Output spectrum: BLA, nonlinear and noise levels")
    return fig


def plot_output_spectrum(result, path, title=None, unit="unit"):
    """:func:`figure3` written to ``path``; returns the path."""
    return _save(figure3(result, title, unit), path)


def figure_bla(result, title=None, g_unit="y/u", band_p=None):
    """One BLA: magnitude with its total and noise standard deviations, phase.

    ``g_unit``: the BLA's unit, output per input (e.g. "rad/V"); the magnitude axis is
    in dB re 1 ``g_unit``. ``band_p`` (e.g. 0.95): also the confidence band of |G| and of
    the phase at that probability, shaded: a circle of radius r = sqrt(s2_BLA ln(1 / (1 -
    p))) around G (the estimate's error taken circular complex normal with variance
    s2_BLA = ``var_total``: P(|error| > r) = exp(-r^2 / s2_BLA) = 1 - p)."""
    fig, (ax_m, ax_p) = _figure(rows=2, height=3.0)
    G = np.asarray(result.G)
    phase = np.degrees(np.unwrap(np.angle(G)))
    if band_p is not None:
        if not 0.0 < band_p < 1.0:
            raise InputError(f"figure_bla: band_p must be in (0, 1), got {band_p!r}")
        if result.var_total is None:
            raise InputError("figure_bla: a confidence band needs the BLA's variance (var_total): "
                             "at least two realizations")
        r = np.sqrt(np.asarray(result.var_total, dtype=float) * np.log(1.0 / (1.0 - band_p)))
        mag = np.abs(G)
        with np.errstate(divide="ignore", invalid="ignore"):
            lo = np.where(mag > r, 20 * np.log10(np.maximum(mag - r, 1e-300)), np.nan)
            dphi = np.degrees(np.where(mag > r, np.arcsin(np.minimum(r / mag, 1.0)), np.pi))
        ax_m.fill_between(result.freq, np.where(np.isfinite(lo), lo, np.nanmin(_db20(G)) - 40.0),
                          _db20(mag + r), color="tab:blue", alpha=0.25, lw=0,
                          label=f"{100 * band_p:g} % confidence band")
        ax_p.fill_between(result.freq, phase - dphi, phase + dphi, color="tab:blue", alpha=0.25,
                          lw=0, label=f"{100 * band_p:g} % confidence band")
    ax_m.plot(result.freq, _db20(G), "k", label="G_BLA")
    if result.var_total is not None:
        ax_m.plot(result.freq, _db10(result.var_total), "tab:red", lw=0.8,
                  label="std total (s2_BLA)")
    if result.var_noise is not None:
        ax_m.plot(result.freq, _db10(result.var_noise), "tab:green", lw=0.8,
                  label="std noise (s2_BLA,n)")
    ax_m.set_ylabel(f"|G| (dB re 1 {g_unit})")
    _legend_outside(ax_m)
    ax_p.plot(result.freq, phase, "k", label="G_BLA")
    ax_p.set_ylabel("phase (deg)")
    if band_p is not None:
        _legend_outside(ax_p)
    for ax in (ax_m, ax_p):
        _plain_log_axis(ax)
        ax.grid(True, which="both", alpha=0.3)
    ax_p.set_xlabel("frequency (Hz)")
    ax_m.set_title(title or "Best linear approximation")
    return fig


def figure_error_spectrum(fs, errors, title=None, unit="rad", f0=None, n_harmonics=25):
    """Amplitude spectra of tracking errors (one line each), e.g. the loop without and
    with the feed-forward.

    Parameters
    ----------
    fs : float
        Sample rate (Hz).
    errors : dict of str -> array_like (n,)
        Label -> tracking error record (whole periods of the excitation: the spectrum is
        the record's DFT, no window; amplitude 2 |X_k| / n of a sine at line k).
    unit : str
        Unit of the error (dB re 1 ``unit`` amplitude).
    f0 : float, optional
        The excitation's frequency (Hz): only its harmonics 1 .. ``n_harmonics`` are drawn
        (markers; the periodic part of the error), else every line up to fs/2.
    """
    fig, (ax,) = _figure(height=3.2)
    n0 = None
    floor = None
    for label, e in errors.items():
        e = np.asarray(e, dtype=float).reshape(-1)
        if n0 is None:
            n0 = e.size
        if e.size != n0 or e.size < 4:
            raise InputError(f"figure_error_spectrum: error {label!r} has {e.size} samples, "
                             f"expected {n0} (at least 4)")
        X = np.fft.rfft(e - e.mean())
        f = np.arange(X.size) * float(fs) / e.size
        amp = 2.0 * np.abs(X) / e.size
        if f0 is not None:
            k = np.rint(np.arange(1, n_harmonics + 1) * f0 * e.size / float(fs)).astype(int)
            k = k[(k > 0) & (k < X.size)]
            f, amp = f[k], amp[k]
            style = dict(marker="o", ms=3, ls="none")
        else:
            f, amp = f[1:], amp[1:]
            style = dict(lw=0.8)
        db = _db20(np.maximum(amp, 1e-15))
        floor = db.max() - 120.0 if floor is None else max(floor, db.max() - 120.0)
        ax.plot(f, db, label=label, **style)
    if floor is not None:
        ax.set_ylim(bottom=floor)
    _plain_log_axis(ax)
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel(f"error amplitude (dB re 1 {unit})")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(0.0, -0.3), borderaxespad=0.0, fontsize=9)
    ax.set_title(title or "Tracking-error spectrum")
    return fig


def plot_bla(result, path, title=None, g_unit="y/u", band_p=None):
    """:func:`figure_bla` written to ``path``."""
    return _save(figure_bla(result, title, g_unit, band_p), path)


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
        _plain_log_axis(ax)
        ax.grid(True, which="both", alpha=0.3)
    _legend_outside(ax_m, fontsize=8, title="excitation", title_fontsize=8)
    ax_m.set_title(title or "BLA vs frequency and excitation level")
    return fig


def plot_bla_levels(levels, path, title=None, g_unit="unit/unit", level_unit="unit"):
    """:func:`figure4` written to ``path``."""
    return _save(figure4(levels, title, g_unit, level_unit), path)


def figure5(result, harmonics=(1, 3, 5, 7), frequency_index=None, title=None, unit="unit",
            h_unit="unit/unit", even_harmonics=(2, 4, 6)):
    """Figure 5: |H_k| vs the sine's rms amplitude (peak / sqrt 2, as the paper) at every
    measured frequency (one column each), odd HOSIDFs (top row) and even ones (bottom
    row), mean (solid) and standard deviation over the repeats (dashed).

    Parameters
    ----------
    result : fftune.analysis.hosidf.HosidfResult
        Leading axes (L,) amplitudes, or (L, F) amplitudes x frequencies.
    harmonics, even_harmonics : sequence of int
        The odd (with H_1) and even harmonics drawn (those beyond the result's K are left
        out; an empty ``even_harmonics`` drops the row).
    frequency_index : int, optional
        Only this frequency of an (L, F) result (default: all).
    """
    H, std = np.asarray(result.H), np.asarray(result.H_std)
    amp, f0 = np.asarray(result.amplitude, dtype=float), np.asarray(result.f0, dtype=float)
    if H.ndim == 2:
        H, std, amp = H[:, None], std[:, None], amp.reshape(-1)[:, None]
        f_col = [float(f0.reshape(-1)[0])]
    elif H.ndim == 3:
        amp = np.broadcast_to(amp, H.shape[:2])
        f_col = [float(v) for v in np.broadcast_to(f0, H.shape[:2])[0]]
    else:
        raise InputError(f"plot_hosidf_amplitude: expected H shaped (L, K) or (L, F, K), got {H.shape}")
    cols = range(H.shape[1]) if frequency_index is None else [frequency_index]
    K = H.shape[-1]
    for k in harmonics:
        if k > K:
            raise InputError(f"plot_hosidf_amplitude: harmonic {k} not in the result")
    even = [k for k in even_harmonics if k <= K]
    rows = 2 if even else 1
    ncol = len(cols)
    fig = Figure(figsize=(max(8.0, 3.2 * ncol), 3.0 * rows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = np.array([[fig.add_subplot(rows, ncol, r * ncol + c + 1) for c in range(ncol)]
                     for r in range(rows)])
    colours = {}
    for c, fi in enumerate(cols):
        a = amp[:, fi] / np.sqrt(2.0)            # peak -> rms
        order = np.argsort(a)
        for r, ks in enumerate([harmonics] + ([even] if even else [])):
            ax = axes[r, c]
            means = np.array([_db20(H[order, fi, k - 1]) for k in ks])
            finite = means[np.isfinite(means)]
            # a standard deviation far under every mean (a deterministic simulation repeats
            # itself to the last bit) is drawn at the panel's floor, not at -400 dB
            floor = (finite.min() - 40.0) if finite.size else -200.0
            for k, m in zip(ks, means):
                line, = ax.plot(a[order], m, "-o", ms=3, color=colours.get(k), label=f"H_{k}")
                colours[k] = line.get_color()
                sd = _db20(std[order, fi, k - 1])
                ax.plot(a[order], np.maximum(np.where(np.isfinite(sd), sd, floor), floor), "--",
                        color=line.get_color(), lw=0.8)
            _plain_log_axis(ax)
            ax.grid(True, which="both", alpha=0.3)
            if c == 0:
                ax.set_ylabel(f"|H_k| (dB re 1 {h_unit})")
            if c == ncol - 1:
                _legend_outside(ax, title="odd" if r == 0 else "even", title_fontsize=7)
            if r == rows - 1:
                ax.set_xlabel(f"sine amplitude ({unit} rms)")
            if r == 0:
                ax.set_title(f"{f_col[fi]:g} Hz", fontsize=9)
    fig.suptitle(title or "HOSIDFs vs amplitude at each frequency: mean (-) and std (--)", fontsize=10)
    return fig


def plot_hosidf_amplitude(result, path, harmonics=(1, 3, 5, 7), frequency_index=None,
                          title=None, unit="unit", h_unit="unit/unit", even_harmonics=(2, 4, 6)):
    """:func:`figure5` written to ``path``."""
    return _save(figure5(result, harmonics, frequency_index, title, unit, h_unit,
                         even_harmonics), path)


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
    _legend_outside(ax_m)
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
            title=None, even_harmonics=None):
    """Figure 7 (and 8): |H_i| and unwrapped phases of the odd HOSIDFs and their level
    relative to H_1 (in %) vs K_fc.

    Parameters
    ----------
    k_fc : array_like, shape (n,)
        Feed-forward gains of the experiments (V).
    H : array_like of complex, shape (n, K)
        HOSIDFs at each K_fc (rad/rad: reference -> motor angle).
    ratio : array_like, shape (n,), optional
        The objective r per experiment; computed with
        :func:`fftune.analysis.tuning.odd_ratio` if omitted.
    k_star : float, optional
        K_fc* to mark.
    harmonics : sequence of int
    H_std : array_like, shape (n, K), optional
        Standard deviations (plotted as dots, as the paper's Figure 8).
    even_harmonics : sequence of int, optional
        Also the even level (rms of these |H_k| over |H_1|) in the bottom panel.

    Phases are unwrapped along K_fc (sorted), so a small step across +-180 deg is drawn as
    the small step it is and the turn at the optimum as the 180 deg it is.
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
        line, = ax_m.plot(k_fc, np.abs(H[:, k - 1]), "-o", ms=3, label=f"|H_{k}| mean")
        if H_std is not None:
            ax_m.plot(k_fc, np.asarray(H_std)[order, k - 1], ".", color=line.get_color(),
                      label=f"std of H_{k}")
        ax_p.plot(k_fc, np.degrees(np.unwrap(np.angle(H[:, k - 1]))), "-o", ms=3,
                  color=line.get_color(), label=f"H_{k}")
    ratio = odd_ratio(H, harmonics) if ratio is None else np.asarray(ratio, dtype=float)[order]
    ax_r.plot(k_fc, 100 * ratio, "k-o", ms=3,
              label="odd: rms(|H_" + "|, |H_".join(str(k) for k in harmonics) + "|) / |H_1|")
    if even_harmonics:
        ax_r.plot(k_fc, 100 * odd_ratio(H, even_harmonics), "-s", color="tab:purple", ms=3,
                  label="even: rms(|H_" + "|, |H_".join(str(k) for k in even_harmonics) + "|) / |H_1|")
    ax_m.set_ylabel("|H_k| (rad/rad)")
    ax_p.set_ylabel("phase, unwrapped (deg)")
    ax_r.set_ylabel("level re |H_1| (%)")
    ax_r.set_xlabel("K_fc (V)")
    for ax in (ax_m, ax_p, ax_r):
        ax.grid(True, alpha=0.3)
        if k_star is not None:
            ax.axvline(k_star, color="tab:red", lw=0.8, ls="--",
                       label=f"K_fc* = {k_star:.4g} V" if ax is ax_r else None)
        _legend_outside(ax)
    ax_m.set_title(title or "Odd HOSIDFs vs Coulomb feed forward K_fc")
    return fig


def figure8(k_fc, H, H_std=None, *, k_star=None, harmonics=(3, 5, 7), even_harmonics=(2, 4, 6),
            title=None):
    """Figure 8 style: :func:`figure7` with the standard deviations as dots and the even
    level beside the odd one (the paper: "even nonlinearities ... 4 %, not influenced")."""
    K = np.asarray(H).shape[-1]
    return figure7(k_fc, H, None, k_star=k_star, harmonics=harmonics, H_std=H_std,
                   even_harmonics=[k for k in even_harmonics if k <= K],
                   title=title or "Set-up: odd HOSIDFs and odd / even levels vs K_fc "
                                  "(mean, dots: std)")


def plot_tuning(k_fc, H, path, ratio=None, *, k_star=None, harmonics=(3, 5, 7), H_std=None,
                title=None):
    """:func:`figure7` written to ``path``."""
    return _save(figure7(k_fc, H, ratio, k_star=k_star, harmonics=harmonics, H_std=H_std,
                         title=title), path)


def figure9(fs, reference, outputs, errors=None, title=None, rms_in_legend=True):
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
    rms_in_legend : bool
        Append each error's rms over the record to its label (off when the labels carry
        the caller's own figure, so that one quantity shows one number).
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
        line, = ax_y.plot(t, y, lw=1, label=f"{label} (rms error {np.sqrt(np.mean(err ** 2)):.3g} rad)"
                          if rms_in_legend else label)
        ax_e.plot(t, err, lw=1, color=line.get_color())
    ax_y.set_ylabel("motor angle (rad)")
    ax_e.set_ylabel("tracking error (rad)")
    ax_e.set_xlabel("time (s)")
    for ax in (ax_y, ax_e):
        ax.grid(True, alpha=0.3)
    # one legend for both panels (the same lines), under the error panel: long labels
    # (the feed-forward in the loop) take the page's width, not the plots'
    handles, labels = ax_y.get_legend_handles_labels()
    ax_e.legend(handles, labels, loc="upper left", bbox_to_anchor=(0.0, -0.25),
                borderaxespad=0.0, fontsize=9)
    ax_y.set_title(title or "Closed-loop response for several K_fc")
    return fig


def plot_time_response(fs, reference, outputs, path, errors=None, title=None, rms_in_legend=True):
    """:func:`figure9` written to ``path``."""
    return _save(figure9(fs, reference, outputs, errors, title, rms_in_legend), path)


def figure_sensitivity(curves, title=None):
    """The measured sensitivity |S| (dB) vs frequency, one line per curve, with 0 dB and
    each curve's peak (M_s) marked.

    Parameters
    ----------
    curves : dict of str -> (freq, S)
        Label -> the lines (Hz) and the complex sensitivity there
        (:func:`fftune.analysis.loop.sensitivity`).
    """
    fig, (ax,) = _figure(height=3.4)
    if not curves:
        raise InputError("figure_sensitivity: no curve")
    for i, (label, (f, S)) in enumerate(curves.items()):
        db = _db20(np.asarray(S))
        k = int(np.nanargmax(db))
        line, = ax.plot(f, db, lw=1.0, label=f"{label}: peak {db[k]:+.1f} dB at {f[k]:.3g} Hz")
        ax.plot([f[k]], [db[k]], "o", mfc="none", color=line.get_color())
    ax.axhline(0.0, color="k", lw=0.6)
    _plain_log_axis(ax)
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("|S| (dB)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(0.0, -0.3), borderaxespad=0.0, fontsize=9)
    ax.set_title(title or "Measured sensitivity of the loop")
    return fig
