"""fftune.analysis: numerical methods for nonlinear motion systems.

Random odd multisines, the robust Best Linear Approximation with noise and nonlinear
variances, odd/even nonlinearity detection, HOSIDFs and the friction feed-forward tuning
objective. Functions work on numpy arrays from any source (as :mod:`scipy.signal` does);
the package imports no CAN code.

Excitation
----------
random_odd_multisine   -- M realizations of a random odd multisine (paper eq. 2).
design_multisine       -- general designer (kinds, bands, amplitude spectra, crest factor).
multisine_realizations -- M realizations of :func:`design_multisine`.
drive_multisine        -- exactly what the drive plays (docs/multisine.md).
crest_factor           -- max|x| / rms(x).

Best Linear Approximation
-------------------------
robust_bla             -- robust BLA with total, noise and nonlinear variances.
bla_levels             -- robust BLA at several excitation levels.
detect_excited_lines   -- excited DFT bins of a periodic multisine.
robust_bla_spectra     -- the same from per-period spectra at the band's lines.
robust_bla_moments     -- the same from line moments (a drive's line statistics).
robust_bla_mimo        -- robust MIMO BLA: n_u inputs, M = B n_u realizations.
LineMoments            -- per-realization means and (co)variances over periods at lines.
classify_grid          -- which odd/even claims an excitation grid allows.
level_verdict          -- the cause a level's detection supports (plant, saturation ...).

Checks before averaging, and the local polynomial method (issue 31)
--------------------------------------------------------------------
check_blocks           -- every block/period/repeat against the others (bursts, gaps,
                          level steps, realizations, off-grid) before averaging.
check_arguments        -- the one argument check of every BLA and HOSIDF entry.
amplitude_levels       -- repeats grouped by level.
lpm_moments            -- robust LPM: line moments with the transient/drift removed.

Higher order sinusoidal input describing functions
--------------------------------------------------
hosidf                 -- H_1 .. H_K with mean and standard deviation over repeats.

Line statistics (what the drive accumulates instead of recording)
-----------------------------------------------------------------
harmonic_stats         -- per-period DFT at k f0: mean and variance over periods, in float64.
parse_stats            -- the drive's statistics upload (object 0x2041).
hosidf_from_stats      -- the HOSIDFs of :func:`hosidf` from line statistics.
LineStats, parse_line_stats, line_stats -- multisine line statistics (object 0x2043).
line_moments           -- LineMoments of M realizations from their LineStats.

Feed-forward tuning
-------------------
odd_ratio              -- rms of |H_3|, |H_5|, |H_7| over |H_1| (objective).
signed_odd_ratio       -- signed objective: > 0 under-, < 0 over-compensated.
RatioMinimizer, SignedRootSearch -- K_fc searches (ask/tell).

Captures
--------
read_run, write_run, load_experiment, export_mat, export_csv -- the HDF5 capture format
(docs/capture-format.md) and its MATLAB / CSV exports.

Plots live in :mod:`fftune.analysis.plots` (imported on demand: matplotlib is slow to load).
"""

import importlib

from fftune import __version__  # noqa: F401  (one version: the distribution's)
from fftune.analysis.errors import FftuneError, InputError
# eager: the function `hosidf` shadows its submodule's name, which a later first import of
# the submodule would otherwise bind here (numpy only)
from fftune.analysis.hosidf import HosidfResult, hosidf

# The other public names and the module each lives in, imported on first use (PEP 562,
# as scipy does): `fftune --version` or `fftune sim` need not load scipy.
_LAZY = {
    "fftune.analysis.bla": ("BLALevels", "BLAResult", "TransientWarning", "bla_levels",
                            "classify_grid", "detect_excited_lines", "level_verdict",
                            "robust_bla", "robust_bla_spectra", "robust_bla_moments",
                            "LineMoments", "robust_bla_mimo", "MimoBLAResult"),
    "fftune.analysis.checks": ("BlockLayout", "amplitude_levels", "check_arguments",
                               "check_blocks"),
    "fftune.analysis.lpm": ("LPMInfo", "lpm_moments"),
    "fftune.analysis.capture": ("export_csv", "export_mat", "load_experiment", "read_run",
                                "write_run"),
    "fftune.analysis.multisine": ("Multisine", "crest_factor", "design_multisine",
                                  "drive_multisine", "multisine_realizations",
                                  "random_odd_multisine"),
    "fftune.analysis.stats": ("HarmonicStats", "harmonic_stats", "hosidf_from_stats",
                              "parse_stats", "LineStats", "line_stats", "parse_line_stats",
                              "line_moments"),
    "fftune.analysis.tuning": ("RatioMinimizer", "SignedRootSearch", "TuningResult",
                               "odd_ratio", "signed_odd_ratio"),
}
_MODULE_OF = {name: mod for mod, names in _LAZY.items() for name in names}


def __getattr__(name):
    mod = _MODULE_OF.get(name)
    if mod is None:
        raise AttributeError(f"module 'fftune.analysis' has no attribute {name!r}")
    value = getattr(importlib.import_module(mod), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))


__all__ = [
    "random_odd_multisine", "design_multisine", "multisine_realizations", "drive_multisine",
    "crest_factor", "Multisine",
    "robust_bla", "robust_bla_spectra", "bla_levels", "detect_excited_lines",
    "classify_grid", "level_verdict", "BLAResult", "BLALevels",
    "TransientWarning",
    "hosidf", "HosidfResult",
    "robust_bla_moments", "LineMoments", "robust_bla_mimo", "MimoBLAResult",
    "harmonic_stats", "parse_stats", "hosidf_from_stats", "HarmonicStats",
    "LineStats", "parse_line_stats", "line_stats", "line_moments",
    "odd_ratio", "signed_odd_ratio", "RatioMinimizer", "SignedRootSearch", "TuningResult",
    "read_run", "write_run", "load_experiment", "export_mat", "export_csv",
    "FftuneError", "InputError",
    "check_blocks", "check_arguments", "amplitude_levels", "BlockLayout",
    "lpm_moments", "LPMInfo",
]
