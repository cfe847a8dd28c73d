"""No test runs a stale firmware_sim binary: the products the Python tests run or load are
checked against their sources with ``make -q`` when a pytest session starts (conftest.py
``pytest_configure``) and rebuilt when older than a prerequisite.

``make test`` builds every product first (firmware_sim's ``test-build``), so there it finds
nothing to do; a targeted ``pytest tests/test_host_cleanup.py`` after an edit of a C source
(with ``make all``, which does not build the sanitizer build, or no make at all) rebuilds
``build/asan/drive_sim`` and the others before any test starts. Only products that exist are
checked: a missing one is the tests' own skip ("not built (run `make setup`)"); without
make (a test guest that has none) nothing is checked.
"""
import fcntl
import os
import shutil
import subprocess
import sys

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir))
FW_DIR = os.path.join(REPO, "firmware_sim")
# firmware_sim make targets the Python tests run or load: drive_sim (conftest.py,
# host_fixtures.py, fftune's drive_sim_path), its ASan + UBSan build (preferred by
# test_reliability_support.py when it exists), libfwsim.so (fwsim.py) and the generated
# od_params.h / EDS (one rule makes both)
FW_PRODUCTS = ("build/gen/od_params.h", "build/libfwsim.so", "build/drive_sim", "build/asan/drive_sim")


def _make(fw_dir, *args, capture=False):
    return subprocess.run(["make", "--no-print-directory", "-C", fw_dir, f"PYTHON={sys.executable}", *args],
                          stdout=subprocess.PIPE if capture else subprocess.DEVNULL,
                          stderr=subprocess.STDOUT if capture else subprocess.DEVNULL, text=True)


def stale_products(fw_dir=FW_DIR, products=FW_PRODUCTS):
    """The products (make targets relative to ``fw_dir``) that exist and are not up to date
    with their prerequisites (``make -q`` exits non-zero), in the order given."""
    return [p for p in products
            if os.path.exists(os.path.join(fw_dir, p)) and _make(fw_dir, "-q", p).returncode != 0]


def rebuild_stale(fw_dir=FW_DIR, products=FW_PRODUCTS):
    """Rebuild every stale product; returns the list rebuilt.

    A lock file (``<fw_dir>/build/.pytest-rebuild.lock``) keeps two pytest sessions of one
    checkout from building at once. Raises RuntimeError with make's last lines when the
    build fails (a C source that does not compile: no test may run the old binary)."""
    build = os.path.join(fw_dir, "build")
    if not os.path.isdir(build) or shutil.which("make") is None:
        return []           # (nothing built here, or no make: e.g. a test guest without one)
    if not stale_products(fw_dir, products):
        return []           # (the usual case: no lock file written, e.g. on a read-only share)
    with open(os.path.join(build, ".pytest-rebuild.lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        stale = stale_products(fw_dir, products)
        if stale:
            r = _make(fw_dir, *stale, capture=True)
            if r.returncode != 0:
                tail = "\n".join(r.stdout.strip().splitlines()[-15:])
                raise RuntimeError(f"make -C {fw_dir} {' '.join(stale)} failed (the binaries are older "
                                   f"than their sources; no test runs them):\n{tail}")
        return stale
