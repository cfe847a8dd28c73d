"""``fftune analyze bla|hosidf FILE``: offline analysis of measured data from any source.

Registered in host/cli.py (SUBCOMMAND_MODULES). Signals are laid out realization after
realization (repeat after repeat for ``hosidf``), each with T + P periods of N samples.
Bad input raises :class:`fftune.analysis.errors.InputError` (one line, exit code 2); outputs are
written atomically and only after the analysis succeeded.
"""
import argparse
import json
import os
import sys
import warnings
from pathlib import Path

import numpy as np

from fftune.analysis.errors import InputError

__all__ = ["add_parser", "run_bla", "run_hosidf", "parse_columns", "bla_to_json",
           "hosidf_to_json"]

_CAPTURE_DEFAULTS = {"bla": {"u": "plant_input", "y": "motor_angle", "r": "reference"},
                     "hosidf": {"u": "reference", "y": "motor_angle"}}


def _positive_float(text):
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not np.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be a positive number")
    return value


def _int_at_least(minimum):
    import argparse

    def parse(text):
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"{value} must be >= {minimum}")
        return value
    return parse


class _DeprecatedAlias(argparse.Action):
    """Store the value and say on stderr that the option was renamed."""

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"fftune: warning: {option_string} is deprecated, use --settle-periods "
              f"(the library's settle_periods)", file=sys.stderr)
        setattr(namespace, self.dest, values)


def add_parser(subparsers):
    """Add ``analyze`` with its ``bla`` and ``hosidf`` subcommands."""
    p = subparsers.add_parser(
        "analyze", help="offline analysis of measured data (robust BLA, HOSIDF)",
        description="Analyse measured data from a CSV (with header), NPZ, MAT or fftune "
                    "capture (.h5) file, or a directory of capture runs. Signals are laid out "
                    "realization after realization, each with T + P periods of N samples.")
    sub = p.add_subparsers(dest="analysis", metavar="ANALYSIS", required=True)

    def common(q, what):
        q.add_argument("file", metavar="FILE",
                       help="CSV (header), .npz, .mat, capture .h5, or a directory of "
                            "capture runs (one experiment and level; realizations by index)")
        q.add_argument("--fs", type=_positive_float, metavar="HZ",
                       help="sample rate in Hz (default: from the file)")
        q.add_argument("--period", type=_int_at_least(4), metavar="N",
                       help="samples per period N (default: from the file)")
        q.add_argument("--periods", type=_int_at_least(1), metavar="P",
                       help="steady-state periods P per " + what +
                            " (default: what the record holds after T)")
        q.add_argument("--realizations", type=_int_at_least(1), metavar="M",
                       help=what + "s M in the record (default: from the file, else 1)")
        q.add_argument("--settle-periods", type=_int_at_least(0), metavar="T",
                       dest="settle_periods",
                       help="settle periods T dropped at the start of each " + what +
                            " (the library's settle_periods; default: from the file, else 0)")
        # the old name, kept working (deprecated: the library calls them settle_periods)
        q.add_argument("--skip-periods", type=_int_at_least(0), dest="settle_periods",
                       action=_DeprecatedAlias, help=argparse.SUPPRESS)
        q.add_argument("--experiment", metavar="KIND",
                       help="directory of captures: use only runs of this experiment "
                            "(detect, quantify, tune)")
        q.add_argument("--level", type=_int_at_least(0), metavar="L", dest="level_index",
                       help="directory of captures: use only runs of this level index")
        q.add_argument("--json", metavar="PATH", help="write the results as JSON")
        q.add_argument("--plot", metavar="DIR", help="write figures (PNG) into DIR")

    b = sub.add_parser("bla", help="robust BLA, noise and nonlinear variances, odd/even detection")
    common(b, "realization")
    b.add_argument("--columns", metavar="u=NAME,y=NAME[,r=NAME]",
                   help="signals to use: input u, output y, reference r (closed loop, "
                        "known-reference estimate). Default: u, y (and r if present); "
                        "capture files: plant_input, motor_angle, reference")
    b.add_argument("--lines", metavar="FILE",
                   help="excited lines (integer DFT bins of one period) instead of detecting "
                        "them from the u (or r) spectrum")
    b.add_argument("--y-step", type=_positive_float, metavar="Q", dest="y_step",
                   help="quantisation step of y (e.g. an encoder's 2 pi / counts in rad): its "
                        "periodic error is not taken for plant distortion. Default: found "
                        "from y when its values lie on a grid")
    b.set_defaults(func=run_bla)

    h = sub.add_parser("hosidf", help="HOSIDF H_1..H_K of a sine experiment, mean/std over repeats")
    common(h, "repeat")
    h.add_argument("--columns", metavar="u=NAME,y=NAME",
                   help="input u (the sine) and output y. Default: u, y; capture files: "
                        "reference, motor_angle")
    h.add_argument("--harmonics", type=_int_at_least(1), default=7, metavar="K",
                   help="highest harmonic K (default 7)")
    h.set_defaults(func=run_hosidf)


def parse_columns(text, allowed):
    """Parse ``u=NAME,y=NAME[,r=NAME]`` into a dict; InputError on bad syntax."""
    out = {}
    for item in text.split(","):
        key, sep, name = item.partition("=")
        key, name = key.strip(), name.strip()
        if not sep or not name:
            raise InputError(f"--columns: {item!r} is not ROLE=NAME (e.g. u=current,y=angle)")
        if key not in allowed:
            raise InputError(f"--columns: unknown role {key!r} (use {', '.join(allowed)})")
        if key in out:
            raise InputError(f"--columns: role {key!r} given twice")
        out[key] = name
    for key in ("u", "y"):
        if key not in out:
            raise InputError(f"--columns: role {key!r} missing (need u=NAME,y=NAME)")
    return out


def _select(loaded, args, kind):
    from fftune.analysis.capture import STANDARD_SIGNALS

    allowed = ("u", "y", "r") if kind == "bla" else ("u", "y")
    names = loaded.signals
    if args.columns:
        columns = parse_columns(args.columns, allowed)
    elif set(STANDARD_SIGNALS) & set(names) and "u" not in names:
        columns = {k: v for k, v in _CAPTURE_DEFAULTS[kind].items() if k in ("u", "y") or v in names}
    else:
        columns = {"u": "u", "y": "y"}
        if kind == "bla" and "r" in names:
            columns["r"] = "r"
    for role, name in columns.items():
        if name not in names:
            raise InputError(f"{loaded.path}: no column/signal {name!r} for {role} "
                             f"(available: {', '.join(names)}); use --columns")
    lengths = {names[c].size for c in columns.values()}
    if len(lengths) != 1:
        raise InputError(f"{loaded.path}: signals {', '.join(columns.values())} have different "
                         f"lengths {sorted(lengths)}")
    return {role: names[name] for role, name in columns.items()}, columns


def _layout(loaded, args, n_samples, kind):
    fs = args.fs if args.fs is not None else loaded.fs_hz
    if loaded.time_fs_hz is not None:
        if fs is None:
            fs = loaded.time_fs_hz
        elif abs(fs - loaded.time_fs_hz) > 1e-3 * loaded.time_fs_hz:
            given = "--fs" if args.fs is not None else "the file's fs_hz"
            raise InputError(f"{loaded.path}: {given} {fs:g} Hz disagrees with the time column "
                             f"{loaded.time_column!r} ({loaded.time_fs_hz:g} Hz from its "
                             f"spacing)")
    if fs is None:
        raise InputError(f"{loaded.path}: sample rate unknown: give --fs HZ")
    lay = loaded.layout
    m = args.realizations or lay.get("realizations") or 1
    t = args.settle_periods if args.settle_periods is not None else lay.get("settle_periods", 0)
    n = args.period or lay.get("n_period")
    p = args.periods
    if p is None and n is not None and "record_periods" in lay and lay.get("n_period") == n \
            and args.settle_periods is None:
        p = lay["record_periods"]
    if n is None:
        if kind == "bla":
            raise InputError(f"{loaded.path}: samples per period unknown: give --period N")
        blocks = (t + (p or 1))
        if n_samples % (m * blocks):
            raise InputError(f"{loaded.path}: {n_samples} samples per signal cannot be split into "
                             f"M = {m} x {blocks} periods")
        n = n_samples // (m * blocks)
        p = p or 1
    if p is None:
        if n_samples % (m * n):
            raise InputError(f"{loaded.path}: the period N = {n} does not divide the record: "
                             f"{n_samples} samples per signal is not a multiple of M x N = "
                             f"{m} x {n}")
        p = n_samples // (m * n) - t
        if p < 1:
            raise InputError(f"{loaded.path}: {n_samples} samples hold {n_samples // (m * n)} "
                             f"periods per realization, none left after skipping T = {t}")
    if m * (t + p) * n != n_samples:
        raise InputError(f"{loaded.path}: wrong length: {n_samples} samples per signal, expected "
                         f"M x (T+P) x N = {m} x ({t}+{p}) x {n} = {m * (t + p) * n}")
    return float(fs), m, t, p, n


def _matrix_order(loaded, columns, sig, n):
    """MAT and NPZ matrices: a matrix signal must hold whole periods along one dimension:
    along its first (N x P, read column after column: MATLAB's x(:)) or its last (P x N,
    read row after row). The file's own convention is tried first (MATLAB: columns,
    numpy: rows); the other one is taken with a note; any other layout is refused,
    naming it. Returns (signals, notes)."""
    out = dict(sig)
    notes = []
    native = getattr(loaded, "matrix_order", "F")
    for role, name in columns.items():
        arr = loaded.matrices.get(name)
        if arr is None:
            continue
        shape = " x ".join(str(d) for d in arr.shape)
        cols, rows = arr.shape[0] % n == 0, arr.shape[-1] % n == 0
        order = ("F" if cols else "C" if rows else None) if native == "F" else \
            ("C" if rows else "F" if cols else None)
        if order is None:
            raise InputError(
                f"{loaded.path}: {role} = {name!r} is a {shape} matrix and N = {n} samples per "
                f"period fit neither its columns (N x P) nor its rows (P x N): store it as one "
                f"vector, or as " + ("N x P" if native == "F" else "P x N"))
        if order != native:
            out[role] = np.asarray(arr, dtype=np.float64).reshape(-1, order=order)
            if native == "C":
                notes.append(f"{role} = {name!r} ({shape}) read column after column: its "
                             f"columns hold the N = {n} samples of a period (N x P)")
    return out, notes


def _clean(values):
    """Array -> JSON list with NaN/inf as null; None stays None."""
    if values is None:
        return None
    arr = np.asarray(values, dtype=float)
    return [None if not np.isfinite(v) else float(v) for v in arr.reshape(-1)]


def _complex_pairs(values):
    arr = np.asarray(values).reshape(-1)
    return [[float(v.real), float(v.imag)] for v in arr]


def bla_to_json(res):
    """The ``fftune analyze bla --json`` document of a :class:`fftune.analysis.bla.BLAResult`."""
    from fftune.analysis.bla import level_verdict
    summary = dict(res.summary)
    summary.update({
        "fs_hz": res.fs, "n_period": res.n_period, "realizations": res.n_realizations,
        "periods": res.n_periods, "settle_periods": res.settle_periods,
        "known_reference": res.known_reference, "excited_lines": int(res.bins.size),
        "transient_suspect": bool(res.transient.suspect), "notes": list(res.notes),
    })
    summary = {k: (None if isinstance(v, float) and not np.isfinite(v) else v)
               for k, v in summary.items()}
    return {
        "freq": _clean(res.freq),
        "G": _complex_pairs(res.G),
        "var_total": _clean(res.var_total),
        "var_noise": _clean(res.var_noise),
        "var_nl": _clean(res.var_nl),
        "odd_nonexcited": {"freq": _clean(res.odd_freq), "level_db": _clean(res.odd_db),
                           "noise_db": _clean(res.odd_noise_db)},
        "even_nonexcited": {"freq": _clean(res.even_freq), "level_db": _clean(res.even_db),
                            "noise_db": _clean(res.even_noise_db)},
        "summary": summary,
        "nonexcited": {"freq": _clean(res.nonexcited_bins * res.fs / res.n_period),
                       "level_db": _clean(res.nonexcited_db),
                       "noise_db": _clean(res.nonexcited_noise_db),
                       "plant_referred_db": _clean(res.plant_db),
                       "plant_expected_db": _clean(res.plant_expected_db)},
        "verdict": level_verdict(res.summary),
    }


def hosidf_to_json(res):
    """The ``fftune analyze hosidf --json`` document of one experiment's HosidfResult
    (``notes`` only when the checks before averaging handled something)."""
    doc = {
        "f0": float(np.asarray(res.f0).reshape(-1)[0]),
        "amplitude": float(np.asarray(res.amplitude).reshape(-1)[0]),
        "H": _complex_pairs(res.H),
        "H_std": _clean(res.H_std),
    }
    if getattr(res, "notes", None):
        doc["notes"] = list(res.notes)
    return doc


def check_json_target(path):
    """``--json PATH``: one error line before any analysis when PATH cannot be written (an
    empty name, a directory, a missing or unwritable directory)."""
    if path is None:
        return
    p = Path(path)
    if not str(path).strip():
        raise InputError("--json: empty file name")
    if p.is_dir():
        raise InputError(f"--json {path}: is a directory")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise InputError(f"--json {path}: directory {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"--json {path}: directory {parent} is not writable")


def _write_json(path, document):
    from fftune.analysis.capture import atomic_write

    text = json.dumps(document, indent=1, allow_nan=False) + "\n"
    atomic_write(path, lambda tmp: Path(tmp).write_text(text), overwrite=True, suffix=".json")


def _plot_dir(path):
    d = Path(path)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--plot {d}: cannot create the directory ({exc.strerror})") from None
    return d


def _fmt_db(value):
    return "n/a" if value is None else f"{value:+.1f} dB"


def _print_bands(bands, parity):
    """Per-octave table: median and maximum over the noise (a band median hides a strong
    narrow-band nonlinearity)."""
    def cell(c):
        if c["median_re_noise_db"] is None:
            return f"{c['lines']:3d} lines        n/a       "
        return (f"{c['lines']:3d} lines {c['median_re_noise_db']:+6.1f} / "
                f"{c['max_re_noise_db']:+6.1f} dB")
    print("  per octave, non-excited lines re noise (lines, median / max):")
    for b in bands:
        head = f"    {b['f_lo_hz']:g} .. {b['f_hi_hz']:g} Hz".ljust(22)
        if parity:
            print(f"{head}  odd {cell(b['odd'])}  even {cell(b['even'])}  odd re even "
                  f"{_fmt_db(b['odd_re_even_db'])}")
        else:
            print(f"{head}  {cell(b['nonexcited'])}")


def run_bla(args):
    """``fftune analyze bla``."""
    from fftune.analysis.bla import robust_bla
    from fftune.analysis.io import load_lines, load_signals

    check_json_target(args.json)
    loaded = load_signals(args.file, args.experiment, args.level_index)
    sig, columns = _select(loaded, args, "bla")
    fs, m, t, p, n = _layout(loaded, args, sig["u"].size, "bla")
    sig, layout_notes = _matrix_order(loaded, columns, sig, n)
    lines = load_lines(args.lines) if args.lines else None
    shaped = {k: v.reshape(m, t + p, n) for k, v in sig.items()}
    q, q_note = args.y_step, None
    if q is None:
        from fftune.analysis.bla import estimate_quantisation_step
        q = estimate_quantisation_step(shaped["y"])
        if q is not None:
            q_note = f"quantisation step of y found from its values: {q:.6g} (--y-step Q to set it)"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = robust_bla(shaped["u"], shaped["y"], shaped.get("r"), fs=fs, settle_periods=t,
                         excited_bins=lines, y_quantisation_step=q)
    if q_note:
        res.notes.append(q_note)
    res.notes.extend(layout_notes)
    document = bla_to_json(res)
    plot_dir = _plot_dir(args.plot) if args.plot else None
    if args.json:
        _write_json(args.json, document)
    if plot_dir:
        from fftune.analysis import plots
        plots.plot_output_spectrum(res, plot_dir / "bla_output_spectrum.png")
        plots.plot_bla(res, plot_dir / "bla_frf.png", g_unit=f"{columns['y']}/{columns['u']}")
    for w in caught:
        print(f"fftune: warning: {w.message}", file=sys.stderr)
    s = res.summary
    how = "known reference r" if res.known_reference else "known input u"
    # (the layout the estimate used: the checks may have found another one, in a note)
    m, p, t = res.n_realizations, res.n_periods, res.settle_periods
    print(f"BLA of {columns['y']} / {columns['u']} ({how}): M = {m}, P = {p}, T = {t}, N = {n}, "
          f"fs = {fs:g} Hz, {res.bins.size} excited lines "
          f"{res.freq[0]:g} .. {res.freq[-1]:g} Hz")
    print(f"  excitation grid: {s['grid']}")
    print(f"  per line (median, as Figure 3 shows):")
    print(f"    nonlinear level re BLA output : {_fmt_db(s['line_median_nl_re_output_db'])}")
    print(f"    noise level re nonlinear level: {_fmt_db(s['line_median_noise_re_nl_db'])}")
    frac = s["line_fraction_nl_over_noise_6db"]
    print(f"    lines with nonlinear > noise + 6 dB: "
          f"{'n/a' if frac is None else f'{100 * frac:.0f} %'}")
    if s["excited_detected"] is not None:
        print(f"    excited lines var_total re var_noise: "
              f"{_fmt_db(s['excited_line_median_re_noise_db'])} "
              f"({s['excited_lines_over_noise_6db']} of {s['excited_lines']} lines 6 dB over, "
              f"{s['excited_lines_needed']} needed)")
    if s["parity_classifiable"]:
        for kind in ("odd", "even"):
            over = s[f"{kind}_lines_over_noise_6db"]
            print(f"    {(kind + ' non-excited re noise').ljust(30)}: "
                  f"{_fmt_db(s[f'{kind}_line_median_re_noise_db'])} "
                  f"({'n/a' if over is None else over} of {s[f'{kind}_lines']} lines 6 dB over)")
        print(f"    odd re even (power ratio)     : {_fmt_db(s['odd_re_even_db'])}")
    else:
        over = s["nonexcited_lines_over_noise_6db"]
        print(f"    non-excited re noise          : "
              f"{_fmt_db(s['nonexcited_line_median_re_noise_db'])} "
              f"({'n/a' if over is None else over} of {s['nonexcited_lines']} lines 6 dB over; "
              f"no odd/even split with this grid)")
    if s.get("bands"):
        _print_bands(s["bands"], s["parity_classifiable"])
    print(f"  verdict: {document['verdict']['text']}")
    for note in res.notes:
        print(f"  note: {note}")
    return 0


def _quiet_on_broken_pipe(run):
    """A reader that stops early (``fftune analyze ... | head``) ends the output quietly:
    no BrokenPipeError traceback (the rest of the output goes to /dev/null)."""
    import functools

    @functools.wraps(run)
    def wrapper(args):
        try:
            return run(args)
        except BrokenPipeError:
            # (Python's recipe: later writes, and the flush at exit, go to /dev/null)
            devnull = os.open(os.devnull, os.O_WRONLY)
            try:
                os.dup2(devnull, sys.stdout.fileno())
            except (OSError, ValueError, AttributeError):
                pass
            finally:
                os.close(devnull)
            return 0
    return wrapper


run_bla = _quiet_on_broken_pipe(run_bla)


@_quiet_on_broken_pipe
def run_hosidf(args):
    """``fftune analyze hosidf``: the repeats of one file at several amplitudes are split
    into levels (each analysed on its own, printed and in the JSON's ``levels``)."""
    from fftune.analysis.checks import amplitude_levels, check_blocks
    from fftune.analysis.hosidf import hosidf
    from fftune.analysis.io import load_signals

    check_json_target(args.json)
    loaded = load_signals(args.file, args.experiment, args.level_index)
    sig, columns = _select(loaded, args, "hosidf")
    fs, m, t, p, n = _layout(loaded, args, sig["u"].size, "hosidf")
    sig, layout_notes = _matrix_order(loaded, columns, sig, n)
    u = sig["u"].reshape(m, t + p, n)[:, t:, :]
    y = sig["y"].reshape(m, t + p, n)[:, t:, :]
    # levels: repeats at different amplitudes (the checks before averaging, levels kept)
    lay = check_blocks(u, kind="sine", name="input u", group="repeat", block="block", fs=fs,
                       mixed_levels="keep")
    groups = amplitude_levels(lay.levels, tol_db=0.5) if lay.index.shape[0] > 1 else \
        [np.arange(lay.index.shape[0])]
    if len(groups) > 1:
        u, y = lay.apply(u), lay.apply(y)
        results = [hosidf(u[g], y[g], fs=fs, n_harmonics=args.harmonics) for g in groups]
        for res in results:
            res.notes[:0] = lay.notes
    else:
        groups = [np.arange(m)]
        results = [hosidf(u, y, fs=fs, n_harmonics=args.harmonics)]
    documents = [hosidf_to_json(res) for res in results]
    if len(results) > 1:
        for doc, g in zip(documents, groups):
            doc["repeats"] = [int(i) for i in g]
        document = {"levels": documents}
    else:
        document = documents[0]
    plot_dir = _plot_dir(args.plot) if args.plot else None
    if args.json:
        _write_json(args.json, document)
    if plot_dir:
        from fftune.analysis import plots
        if len(results) == 1:
            plots.plot_hosidf_harmonics(results[0], plot_dir / "hosidf_harmonics.png")
        else:
            for i, res in enumerate(results):
                plots.plot_hosidf_harmonics(res, plot_dir / f"hosidf_harmonics_level{i}.png")
    if len(results) > 1:
        print(f"HOSIDF of {columns['y']} / {columns['u']}: {len(results)} amplitude levels "
              f"among the {m} repeats (repeats at one level: within 0.5 dB)")
    for i, (res, doc, g) in enumerate(zip(results, documents, groups)):
        head = "HOSIDF" if len(results) == 1 else f"level {i}: HOSIDF"
        count = len(g)
        print(f"{head} of {columns['y']} / {columns['u']}: f0 = {doc['f0']:g} Hz, "
              f"amplitude = {doc['amplitude']:.4g}, {count} repeat(s) of {p} period(s)"
              + ("" if len(results) == 1 else f" (repeats {_ranges_text(g)})"))
        h1 = abs(res.H[0])
        for k in res.harmonics:
            hk = res.H[k - 1]
            std = res.H_std[k - 1]
            std_text = "" if not np.isfinite(std) else f"  std {std:.3g}"
            print(f"  H_{k}: |H| = {abs(hk):.4g} ({20 * np.log10(max(abs(hk), 1e-300) / h1):+.1f} "
                  f"dB re H_1), phase {np.degrees(np.angle(hk)):+.1f} deg{std_text}")
        if count == 1:
            print("  note: 1 repeat: no standard deviation (null in the JSON)")
        if i == 0 or len(results) == 1:
            for note in res.notes + layout_notes:
                print(f"  note: {note}")
    return 0


def _ranges_text(idx):
    idx = [int(i) for i in idx]
    if len(idx) > 2 and idx == list(range(idx[0], idx[-1] + 1)):
        return f"{idx[0]}..{idx[-1]}"
    return ", ".join(str(i) for i in idx)
