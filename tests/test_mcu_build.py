"""The processor-in-the-loop build (firmware_sim/port/mcu) without running it: the SLCAN
parser's C unit tests on the host, `make pil` sizes, the no-heap / no-OS link, and the
plant configuration compiled in bit for bit (the deployable flags' -fsingle-precision-constant
once rounded it to float: the PIL runs then drifted from drive_sim's after a few runs)."""
import os
import re
import shutil
import struct
import subprocess
import sys

import pytest
import yaml

from mcu_helpers import ELF, FW, MCU_BUILD, PIL_PLANT, build_pil, pil_missing_reason, symbol_address


def test_slcan_parser_unit_tests():
    if shutil.which("cc") is None:
        pytest.skip("no C compiler (cc)")
    r = subprocess.run(["make", "--no-print-directory", "-C", FW, "pil-test"], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    m = re.search(r"(\d+) passed, (\d+) failed", r.stdout)
    assert m and int(m.group(1)) >= 6 and m.group(2) == "0"


needs_arm = pytest.mark.skipif(shutil.which("arm-none-eabi-gcc") is None,
                               reason="arm-none-eabi-gcc not installed (package gcc-arm-none-eabi: sudo make system-deps)")


@needs_arm
def test_make_pil_prints_sizes_and_links_without_heap_or_os():
    out = build_pil()
    m = re.search(r"flash (\d+) bytes .* of 1048576; RAM (\d+) bytes .* \+ (\d+) stack of 131072", out)
    assert m, out
    flash, ram, stack = map(int, m.groups())
    assert 0 < flash < 1048576 and ram + stack <= 131072
    syms = subprocess.run(["arm-none-eabi-nm", ELF], capture_output=True, text=True, check=True).stdout
    names = {line.split()[-1] for line in syms.splitlines()}
    for forbidden in ("malloc", "_malloc_r", "_sbrk", "free", "_write", "printf", "_printf_r", "snprintf"):
        assert forbidden not in names
    for needed in ("drv_step", "co_node_rx", "co_node_process", "slcan_feed", "sim_step", "mcu_systick_handler"):
        assert needed in names


@needs_arm
def test_plant_configuration_is_compiled_in_bit_for_bit():
    build_pil()
    plant = yaml.safe_load(open(PIL_PLANT))
    # pil_config (const, in flash) as the ELF holds it: read the doubles back from the image
    addr = symbol_address("pil_config")
    sections = subprocess.run(["arm-none-eabi-objdump", "-h", ELF], capture_output=True, text=True, check=True).stdout
    image = None
    for line in sections.splitlines():
        p = line.split()
        if len(p) >= 6 and p[1] == ".text":
            vma, off, size = int(p[3], 16), int(p[5], 16), int(p[2], 16)
            if vma <= addr < vma + size:
                with open(ELF, "rb") as f:
                    f.seek(off + addr - vma)
                    image = f.read(184)  # plant_config_t up to the end of plant_params_t.noise_std
    assert image is not None, "pil_config not in .text"
    fs_hz, = struct.unpack_from("<d", image, 0)
    kp, kd, tau_d = struct.unpack_from("<3d", image, 16)
    j1, j2, k, c, km, coulomb = struct.unpack_from("<6d", image, 72)
    assert fs_hz == float(plant["drive"]["fs_hz"])
    assert (kp, kd, tau_d) == (plant["controller"]["kp"], plant["controller"]["kd"], plant["controller"]["tau_d"])
    assert (j1, j2, k, c, km, coulomb) == tuple(float(plant["plant"][n]) for n in ("j1", "j2", "k", "c", "km", "coulomb"))
