"""`make cross` link check of the deployable core: an OS / C-library call fails the link,
libm does not (firmware_sim/Makefile, rules core-cross and core-cross-probe)."""
import os
import shutil
import subprocess

import pytest

FW = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "firmware_sim")

pytestmark = pytest.mark.skipif(shutil.which("arm-none-eabi-gcc") is None,
                                reason="arm-none-eabi-gcc not installed (make system-deps: gcc-arm-none-eabi)")


def probe(tmp_path, body):
    src = tmp_path / "probe.c"
    src.write_text(body)
    return subprocess.run(["make", "--no-print-directory", "-C", FW, "core-cross-probe", f"CROSS_PROBE={src}"],
                          capture_output=True, text=True)


def test_core_cross_builds_and_prints_sizes():
    out = subprocess.run(["make", "--no-print-directory", "-C", FW, "core-cross"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "(TOTALS)" in out.stdout and "sizeof(drv_t) = " in out.stdout


@pytest.mark.parametrize("call, symbol", [("malloc(4)", "malloc"), ("(void *)(long)printf(\"x\")", "printf"),
                                          ("(void *)(long)time(0)", "time")])
def test_os_call_fails_the_link(tmp_path, call, symbol):
    res = probe(tmp_path, "#include <stdio.h>\n#include <stdlib.h>\n#include <time.h>\n"
                          f"void *cross_probe(void);\nvoid *cross_probe(void) {{ return {call}; }}\n")
    assert res.returncode != 0
    assert f"undefined reference to `{symbol}'" in res.stderr


def test_libm_links(tmp_path):
    res = probe(tmp_path, "#include <math.h>\nfloat cross_probe(float x);\n"
                          "float cross_probe(float x) { return sinf(x) + cosf(x); }\n")
    assert res.returncode == 0, res.stderr
