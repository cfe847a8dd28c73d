"""The paper's quantitative claims and the numbers that reproduce them (``make paper``).

The host (``fftune.host.paper``) runs the experiments; this module turns their HOSIDFs and
tracking errors into the numbers of ``reproduction.json`` and compares each with the paper:

* :func:`phase_turn_deg` -- how far the phase of H_k turns across K_fc* (Figure 7).
* :func:`min_rms_kfc` -- the K_fc of the smallest rms tracking error (Figure 9).
* :func:`relative_levels` -- odd and even HOSIDF levels relative to H_1 (Figure 8, text).
* :data:`PAPER_CLAIMS` and :func:`compare` -- each claim, its accepted range, the verdict.
* :func:`markdown_table` -- the "paper / measured / agrees?" table of the docs.

Units: K_fc in V, angles in degrees, levels dimensionless (fractions of |H_1|).
"""
import math

import numpy as np

from fftune.analysis.errors import InputError
from fftune.analysis.tuning import harmonic_orders, odd_ratio

__all__ = ["phase_turn_deg", "min_rms_kfc", "relative_levels", "reproduction_numbers",
           "PAPER_CLAIMS", "DETECT_CLAIMS", "detect_numbers", "compare", "markdown_table"]


def _sorted_sweep(k_fc, *arrays):
    k = np.asarray(k_fc, dtype=float)
    if k.ndim != 1 or k.size < 3:
        raise InputError(f"reproduction: a sweep needs at least 3 K_fc values, got shape {k.shape}")
    order = np.argsort(k)
    return (k[order],) + tuple(np.asarray(a)[order] for a in arrays)


def phase_turn_deg(k_fc, H, k_star, harmonic=3):
    """The turn (deg, >= 0) of the phase of H_``harmonic`` across ``k_star``.

    The phase is unwrapped along the sweep (sorted by K_fc) and the turn is the difference
    between the unwrapped phases at the last sweep point below ``k_star`` and the first one
    above it, so a small step across +-180 deg (e.g. +175 to -173) counts as 12 deg, not as a
    flip. With odd harmonics that change sign at the optimum (a relay of height Fc - K_fc)
    the turn is 180 deg.

    Parameters
    ----------
    k_fc : array_like, shape (n,)
        Feed-forward gains of the sweep (V).
    H : array_like of complex, shape (n, K)
        HOSIDFs H_1 .. H_K at each K_fc.
    k_star : float
        The optimum (V); needs sweep points on both sides.
    harmonic : int

    Returns
    -------
    float
    """
    k, H = _sorted_sweep(k_fc, H)
    if H.ndim != 2 or H.shape[-1] < harmonic:
        raise InputError(f"phase_turn_deg: H must be shaped (n, K >= {harmonic}), got {H.shape}")
    below, above = np.flatnonzero(k < k_star), np.flatnonzero(k > k_star)
    if not below.size or not above.size:
        raise InputError(f"phase_turn_deg: K_fc* = {k_star:g} V is not inside the sweep "
                         f"[{k[0]:g}, {k[-1]:g}] V")
    phase = np.unwrap(np.angle(H[:, harmonic - 1]))
    return float(abs(np.degrees(phase[above[0]] - phase[below[-1]])))


def min_rms_kfc(k_fc, rms_error):
    """K_fc (V) of the smallest rms tracking error: the sweep's minimum refined by a parabola
    through it and its two neighbours (the grid minimum at an end of the sweep).

    Returns
    -------
    k_min : float
    at_end : bool
        True when the minimum is at an end of the sweep (it may lie outside).
    """
    k, e = _sorted_sweep(k_fc, rms_error)
    e = np.asarray(e, dtype=float)
    i = int(np.nanargmin(e))
    if i == 0 or i == k.size - 1:
        return float(k[i]), True
    x, y = k[i - 1:i + 2], e[i - 1:i + 2]
    den = (x[0] - x[1]) * (x[0] - x[2]) * (x[1] - x[2])
    a = (x[2] * (y[1] - y[0]) + x[1] * (y[0] - y[2]) + x[0] * (y[2] - y[1])) / den
    b = (x[2] ** 2 * (y[0] - y[1]) + x[1] ** 2 * (y[2] - y[0]) + x[0] ** 2 * (y[1] - y[2])) / den
    if not a > 0:
        return float(k[i]), False
    return float(np.clip(-b / (2 * a), x[0], x[2])), False


def relative_levels(H, n_harmonics=None):
    """Odd and even HOSIDF levels relative to H_1 (the one definition of
    :data:`fftune.analysis.tuning.ODD_LEVEL_DEFINITION`, even: k = 2, 4, .. K).

    Returns
    -------
    odd, even : ndarray, shape H.shape[:-1]
    """
    H = np.asarray(H)
    K = H.shape[-1] if n_harmonics is None else int(n_harmonics)
    if K < 3:
        raise InputError(f"relative_levels: need H_1 .. H_3 at least, got {K} harmonics")
    return (np.asarray(odd_ratio(H, harmonic_orders(K, "odd"))),
            np.asarray(odd_ratio(H, harmonic_orders(K, "even"))))


def _f(x):
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def reproduction_numbers(*, k_star, k_true, k_sweep, H_sweep, rms_sweep, H_at_0, H_at_star,
                         sim_k_star=None, sim_k_sweep=None, sim_H_sweep=None):
    """The numbers of ``reproduction.json`` (SI units: V, deg, fractions).

    Parameters
    ----------
    k_star : float
        K_fc* of the automated search on the set-up (V).
    k_true : float or None
        The simulated plant's Coulomb level (V).
    k_sweep, H_sweep, rms_sweep : array_like
        The paper's sweep on the set-up: K_fc (V), HOSIDFs (n, K), rms tracking error (rad),
        measured with K_v = 0.
    H_at_0, H_at_star : array_like of complex, shape (K,)
        HOSIDFs at K_fc = 0 and at the experiment verifying K_fc*.
    sim_k_star, sim_k_sweep, sim_H_sweep : optional
        The same sweep on the idealised simulation model (the paper's Figure 7); the phase
        turns come from it (``*_setup`` keys: the same on the set-up).

    Returns
    -------
    dict
    """
    k_sweep = np.asarray(k_sweep, dtype=float)
    H_sweep = np.asarray(H_sweep)
    odd0, even0 = relative_levels(np.asarray(H_at_0))
    odd_s, even_s = relative_levels(np.asarray(H_at_star))
    k_rms, rms_at_end = min_rms_kfc(k_sweep, rms_sweep)
    out = {
        "kfc_star_v": _f(k_star), "kfc_true_v": _f(k_true),
        "kfc_star_rel_truth": _f(k_star / k_true - 1) if k_true else None,
        "odd_ratio_at_0": _f(odd0), "odd_ratio_at_star": _f(odd_s),
        "odd_ratio_improvement": _f(odd0 / odd_s) if odd_s > 0 else None,
        "even_ratio_at_0": _f(even0), "even_ratio_at_star": _f(even_s),
        "even_ratio_change": _f(abs(even_s / even0 - 1)) if even0 > 0 else None,
        "min_rms_kfc_v": _f(k_rms), "min_rms_kfc_rel": _f(k_rms / k_star - 1),
        "min_rms_at_sweep_end": bool(rms_at_end),
        "sweep_step_v": _f(np.min(np.diff(np.unique(k_sweep)))),
    }
    for k in (3, 5, 7):
        try:
            out[f"h{k}_phase_turn_deg_setup"] = _f(phase_turn_deg(k_sweep, H_sweep, k_star, k))
        except InputError:
            out[f"h{k}_phase_turn_deg_setup"] = None
    if sim_H_sweep is not None:
        out["sim_kfc_star_v"] = _f(sim_k_star)
        for k in (3, 5, 7):
            try:
                out[f"h{k}_phase_turn_deg"] = _f(phase_turn_deg(sim_k_sweep, sim_H_sweep, sim_k_star, k))
            except InputError:
                out[f"h{k}_phase_turn_deg"] = None
    else:
        for k in (3, 5, 7):
            out[f"h{k}_phase_turn_deg"] = out[f"h{k}_phase_turn_deg_setup"]
    return out


# The paper's claims: key of reproduction.json, what the paper says, the accepted range (the
# acceptance of issue 24), and what the number means. "range" is [low, high] (None: open).
PAPER_CLAIMS = [
    {"key": "kfc_star_rel_truth", "claim": "K_fc* where the feed-forward equals the Coulomb "
     "friction (Figure 7; here the automated search on the set-up, re the simulated Fc)",
     "paper": "K_fc* = Fc", "range": [-0.02, 0.02], "format": "pct_signed"},
    {"key": "odd_ratio_at_0", "claim": "relative odd NL level at K_fc = 0 (Figure 8)",
     "paper": "15 %", "range": [0.10, 0.25], "format": "pct"},
    {"key": "odd_ratio_at_star", "claim": "relative odd NL level at K_fc* (Figure 8)",
     "paper": "< 1.5 %", "range": [None, 0.015], "format": "pct"},
    {"key": "h3_phase_turn_deg", "claim": "phase of H_3 turns at the optimum (simulation, Figure 7)",
     "paper": "180 deg", "range": [160.0, 200.0], "format": "deg"},
    {"key": "h5_phase_turn_deg", "claim": "phase of H_5 turns at the optimum (simulation, Figure 7)",
     "paper": "180 deg", "range": [160.0, 200.0], "format": "deg"},
    {"key": "min_rms_kfc_rel", "claim": "smallest rms tracking error above K_fc* (Figure 9: "
     "0.1444 vs 0.1157 V)", "paper": "+25 %", "range": [0.15, 0.35], "format": "pct_signed"},
    {"key": "even_ratio_at_0", "claim": "relative even NL level at K_fc = 0 (text)",
     "paper": "4 %", "range": [0.02, 0.08], "format": "pct"},
    {"key": "even_ratio_at_star", "claim": "relative even NL level at K_fc* (text)",
     "paper": "4 %", "range": [0.02, 0.08], "format": "pct"},
    {"key": "even_ratio_change", "claim": "even NL not influenced by the odd feed-forward "
     "(|change| from K_fc = 0 to K_fc*)", "paper": "unchanged", "range": [None, 0.30],
     "format": "pct"},
    {"key": "odd_ratio_improvement", "claim": "odd NL reduced about tenfold (Figure 8: 15 % to "
     "< 1.5 %)", "paper": ">= 10x", "range": [10.0, None], "format": "x"},
]


def detect_numbers(detect, level_v_rms=3.72):
    """The Figure 3 numbers (dB) of the detection (results.yaml's ``detect`` block) at the
    level nearest ``level_v_rms`` (the paper's 3.72 V rms); {} without.

    The nonlinear and noise levels are per-line medians; odd over even is the detection's
    one odd-re-even figure, the power ratio of the odd to the even non-excited lines
    (``summary_db.odd_re_even_db``; the per-line median of it is no longer reported). A
    figure the detection does not report is None (the comparison shows n/a, never drops it)."""
    if not detect or not detect.get("levels"):
        return {}
    lv = min(detect["levels"], key=lambda x: abs(x["rms_requested"] - level_v_rms))
    s = lv["summary_db"]
    return {"detect_level_v_rms": lv["rms_requested"],
            "detect_nl_re_output_db": s.get("line_median_nl_re_output_db"),
            "detect_odd_re_even_db": s.get("odd_re_even_db"),
            "detect_noise_re_nl_db": s.get("line_median_noise_re_nl_db")}


# measured by the paper on another set-up (``setup``) than the one reproduced (set-up II):
# shown beside it, not judged (compare: verdict "other set-up")
DETECT_CLAIMS = [
    {"key": "detect_nl_re_output_db", "claim": "nonlinear distortion re BLA output (Figure 3, "
     "TEM stage)", "paper": "-10 dB", "range": [-15.0, -5.0], "format": "db",
     "setup": "the TEM stage (set-up I)"},
    {"key": "detect_odd_re_even_db", "claim": "odd NL over even NL (Figure 3, TEM stage)",
     "paper": "+20 dB", "range": [15.0, 25.0], "format": "db", "setup": "the TEM stage (set-up I)"},
    {"key": "detect_noise_re_nl_db", "claim": "noise re nonlinear distortion (Figure 3, TEM stage)",
     "paper": "-30 dB", "range": [-35.0, -25.0], "format": "db", "setup": "the TEM stage (set-up I)"},
]


def _fmt(v, kind):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    if kind == "pct":
        return f"{100 * v:.3g} %"
    if kind == "pct_signed":
        return f"{100 * v:+.3g} %"
    if kind == "deg":
        return f"{v:.1f} deg"
    if kind == "x":
        return f"{v:.3g}x"
    if kind == "db":
        return f"{v:+.1f} dB"
    return f"{v:.4g}"


def _range_text(rng, kind):
    lo, hi = rng
    if lo is not None and hi is not None:
        if kind == "db":
            return f"{lo:+.0f} .. {hi:+.0f} dB"
        return f"{_fmt(lo, kind)} .. {_fmt(hi, kind)}"
    return f">= {_fmt(lo, kind)}" if lo is not None else f"<= {_fmt(hi, kind)}"


def compare(measured, claims=PAPER_CLAIMS):
    """Each claim with the measured value and whether it lies in the accepted range.

    Parameters
    ----------
    measured : dict
        The reproduction numbers (keys of :data:`PAPER_CLAIMS`; a missing or None value is
        "n/a", not agreeing).

    Returns
    -------
    list of dict
        ``key, claim, paper, measured, measured_text, accepted, agrees, verdict`` per
        claim; ``verdict`` is "yes", "no", or "other set-up" for a claim the paper measured
        on another set-up (the claim's ``setup``: not a failure, shown for reference; its
        ``agrees`` still says whether the number falls in the range).
    """
    rows = []
    for c in claims:
        v = measured.get(c["key"])
        ok = v is not None and math.isfinite(float(v))
        lo, hi = c["range"]
        if ok:
            ok = (lo is None or v >= lo) and (hi is None or v <= hi)
        rows.append({"key": c["key"], "claim": c["claim"], "paper": c["paper"],
                     "measured": None if v is None else float(v),
                     "measured_text": _fmt(None if v is None else float(v), c["format"]),
                     "accepted": _range_text(c["range"], c["format"]), "agrees": bool(ok),
                     "verdict": "other set-up" if c.get("setup") else ("yes" if ok else "no"),
                     "setup": c.get("setup")})
    return rows


def markdown_table(rows, notes=None):
    """The "paper / measured / agrees?" table (Markdown) of :func:`compare`'s rows;
    ``notes`` (key -> text) adds a column saying where and why a result differs."""
    notes = notes or {}
    out = ["| claim | paper | measured | accepted | agrees? | note |", "|---|---|---|---|---|---|"]
    for r in rows:
        note = notes.get(r["key"], "").replace("|", "/").replace("\n", " ")
        verdict = r.get("verdict") or ("yes" if r["agrees"] else "no")
        cell = {"yes": "yes", "no": "**no**"}.get(verdict, f"not compared (the paper: {r.get('setup')})")
        out.append(f"| {r['claim']} | {r['paper']} | {r['measured_text']} | {r['accepted']} | "
                   f"{cell} | {note} |")
    return "\n".join(out)
