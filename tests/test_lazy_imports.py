"""The command line starts without scipy (fftune.analysis loads its public names on first
use, PEP 562): `fftune --version` and `fftune sim` stay quick, also in the TCG guest where
importing scipy.signal takes 25 s. The public API still reads as before."""
import subprocess
import sys


def _run(code):
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)


def test_cli_parser_loads_no_scipy():
    p = _run("import sys\nfrom fftune.host.cli import build_parser\nbuild_parser()\n"
             "print(sorted(m for m in sys.modules if m == 'scipy' or m.startswith('scipy.')))")
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "[]"


def test_public_names_resolve_whatever_was_imported_first():
    p = _run("import fftune.analysis.hosidf, fftune.analysis.stats, fftune.analysis.tuning\n"
             "import fftune.analysis as a\n"
             "from fftune.analysis import hosidf, robust_bla, random_odd_multisine, odd_ratio, parse_stats\n"
             "assert callable(hosidf) and hosidf.__module__ == 'fftune.analysis.hosidf', hosidf\n"
             "missing = [n for n in a.__all__ if not hasattr(a, n)]\n"
             "assert not missing, missing\n"
             "try:\n    a.no_such_name\nexcept AttributeError as e:\n    print(e)\n")
    assert p.returncode == 0, p.stderr
    assert "no attribute 'no_such_name'" in p.stdout
