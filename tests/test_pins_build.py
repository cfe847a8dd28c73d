"""No test runs a stale binary (issue 33).

1. Every header a firmware_sim product is compiled from (as the compiler itself lists it:
   ``cc -MM`` on the product's own compile commands from ``make -n -B``) is a prerequisite
   of that product in the makefiles: ``make -q -W HEADER PRODUCT`` (the header pretended
   new) says the product must be rebuilt. A header missing from a rule (as core/*.h and
   plant/*.h were from build/asan/drive_sim's) leaves a binary that `make test`'s build
   step and conftest's check both think fresh after that header changed.
2. conftest's check (tests/fw_fresh.py) finds a product older than its source and rebuilds
   it, on a scratch makefile (the checkout's build is not touched).
"""
import os
import shlex
import subprocess
import time

import pytest

from fw_fresh import FW_DIR, rebuild_stale, stale_products

# every product `make test` builds and runs, and those the Python tests run
PRODUCTS = ["build/drive_sim", "build/libfwsim.so", "build/test_core", "build/test_plant", "build/co_test",
            "build/asan/drive_sim", "build/asan/test_core", "build/asan/test_plant", "build/asan/co_test",
            "build/asan/replay_co_node"]


def _commands(product):
    """The compiler commands ``make -n -B`` prints for ``product`` (continuations joined)."""
    r = subprocess.run(["make", "--no-print-directory", "-n", "-B", "-C", FW_DIR, "PYTHON=python3", product],
                       capture_output=True, text=True, check=True)
    text = r.stdout.replace("\\\n", " ")
    cmds = []
    for line in text.splitlines():
        first = line.split()[:1]
        if not first or os.path.basename(first[0]) not in ("cc", "gcc", "clang"):
            continue
        words = shlex.split(line)
        if os.path.basename(words[0]) in ("cc", "gcc", "clang") and any(w.endswith(".c") for w in words):
            cmds.append(words)
    return cmds


def _headers(cmd):
    """The project's headers the compile command reads (the compiler's -MM list)."""
    keep = [cmd[0], "-MM"]
    skip = False
    for w in cmd[1:]:
        if skip:
            skip = False
            continue
        if w == "-o":
            skip = True
        elif w == "-c" or w.startswith(("-l", "-M", "-fsanitize", "-shared")) or w.endswith((".a", ".o")):
            continue
        else:
            keep.append(w)
    r = subprocess.run(keep, cwd=FW_DIR, capture_output=True, text=True, check=True)
    deps = r.stdout.replace("\\\n", " ").split()
    out = set()
    for d in deps:
        if d.endswith(".h") and not os.path.isabs(d):
            d = os.path.normpath(d)
            if d.startswith("build/co_double/"):    # copies the co_test double's rule makes
                name = os.path.basename(d)
                d = next(p for p in (f"canopen/tests/{name}", f"core/{name}")
                         if os.path.exists(os.path.join(FW_DIR, p)))
            out.add(d)
    return out


@pytest.mark.parametrize("product", PRODUCTS)
def test_every_header_a_product_reads_is_its_prerequisite(product):
    if not os.path.exists(os.path.join(FW_DIR, product)):
        pytest.skip(f"firmware_sim/{product} not built here (`make test` builds it); "
                    f"`make -q -W` needs the product to exist")
    # (a stale product needs a rebuild whatever -W says: made fresh first, or the check
    # below would pass on it trivially)
    rebuild_stale(FW_DIR, (product,))
    assert stale_products(FW_DIR, (product,)) == []
    cmds = _commands(product)
    assert cmds, f"make -n -B {product}: no compile command"
    headers = set().union(*(_headers(c) for c in cmds))
    # the compiler's list is not empty, and holds headers of the product's own parts
    assert any(h.startswith(("core/", "canopen/", "plant/")) for h in headers), headers
    missing = []
    for h in sorted(headers):
        q = subprocess.run(["make", "-q", "--no-print-directory", "-C", FW_DIR, "PYTHON=python3", "-W", h, product],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        if q.returncode != 1:
            missing.append(h)
    assert not missing, f"{product}: compiled from {missing} but does not depend on them in the makefiles"


def _scratch(tmp_path):
    (tmp_path / "build").mkdir()
    (tmp_path / "src.txt").write_text("one\n")
    (tmp_path / "Makefile").write_text("build/out: src.txt\n\tcp src.txt build/out\n"
                                       "build/other: Makefile\n\ttouch build/other\n")
    subprocess.run(["make", "-s", "-C", str(tmp_path), "build/out", "build/other"], check=True)
    return str(tmp_path)


def test_conftest_check_rebuilds_a_product_older_than_its_source(tmp_path):
    d = _scratch(tmp_path)
    products = ("build/out", "build/other", "build/never_built")
    assert stale_products(d, products) == []
    assert rebuild_stale(d, products) == []
    (tmp_path / "src.txt").write_text("two\n")
    now = time.time()                           # (apart by more than any file system's step)
    os.utime(tmp_path / "src.txt", (now - 50, now - 50))
    os.utime(tmp_path / "build" / "out", (now - 100, now - 100))
    old = os.stat(os.path.join(d, "build", "out")).st_mtime
    # only the product whose source changed; a product never built is not the check's
    assert stale_products(d, products) == ["build/out"]
    assert rebuild_stale(d, products) == ["build/out"]
    assert (tmp_path / "build" / "out").read_text() == "two\n"
    assert os.stat(os.path.join(d, "build", "out")).st_mtime > old
    assert stale_products(d, products) == []


def test_conftest_check_refuses_when_the_rebuild_fails(tmp_path):
    d = _scratch(tmp_path)
    (tmp_path / "Makefile").write_text("build/out: src.txt\n\tfalse  # the C does not compile\n")
    future = time.time() + 5
    os.utime(tmp_path / "src.txt", (future, future))
    with pytest.raises(RuntimeError, match=r"build/out failed .*no test runs them"):
        rebuild_stale(d, ("build/out",))


def test_the_products_this_session_runs_are_fresh():
    """conftest's check ran before this test: every product that exists is up to date with
    its sources (a session that skipped the check after an edit of a C source fails here)."""
    assert stale_products() == []
