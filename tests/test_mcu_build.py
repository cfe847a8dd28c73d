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


def _cfggen(tmp_path, text):
    """Run port/mcu/cfggen (built by make pil) on a plant file with ``text``; (code, stderr, .c text)."""
    build_pil()
    plant = tmp_path / "plant.yaml"
    plant.write_text(text)
    out = tmp_path / "out"
    out.mkdir()
    r = subprocess.run([os.path.join(MCU_BUILD, "cfggen"), str(plant), "3", str(out)], capture_output=True, text=True)
    c_file = out / "pil_config.c"
    return r.returncode, r.stderr, c_file.read_text() if c_file.exists() else None


def _c_double(c_text, field):
    """The hexadecimal floating-point initializer ``.field = 0x...`` of the generated C."""
    m = re.search(r"\." + field + r" = (-?0x[0-9a-fp.+-]+)", c_text)
    assert m, f".{field} missing in:\n{c_text}"
    return float.fromhex(m.group(1))


@needs_arm
def test_cfggen_writes_position_friction_and_drift_bit_for_bit(tmp_path):
    """The MCU build's plant is drive_sim's: coulomb_position and the friction drift
    (drift: section, applied by sim_step on the M4 too) go in bit for bit, unequal values so
    a swapped field fails."""
    code, err, c_text = _cfggen(tmp_path, "drive:\n  fs_hz: 2560\n  rec_capacity: 1000\n  table_capacity: 4096\n"
                                          "plant:\n  coulomb_position: 0.123\n  coulomb_asymmetry: -0.05\n"
                                          "  static: 0.02\n"
                                          "drift:\n  coulomb_step: 0.25\n  coulomb_step_time_s: 3.5\n"
                                          "  coulomb_exp: 0.4\n  coulomb_exp_tau_s: 7.25\n"
                                          "  viscous_ramp: -0.3\n  viscous_ramp_start_s: 1.5\n"
                                          "  viscous_ramp_end_s: 9.75\n")
    assert code == 0, err
    assert _c_double(c_text, "coulomb_pos") == 0.123 and _c_double(c_text, "coulomb_asym") == -0.05
    dc = c_text[c_text.index(".drift_coulomb"):c_text.index(".drift_viscous")]
    dv = c_text[c_text.index(".drift_viscous"):]
    assert (_c_double(dc, "step"), _c_double(dc, "step_time_s"), _c_double(dc, "exp"), _c_double(dc, "exp_tau_s"),
            _c_double(dc, "ramp")) == (0.25, 3.5, 0.4, 7.25, 0.0)
    assert (_c_double(dv, "ramp"), _c_double(dv, "ramp_start_s"), _c_double(dv, "ramp_end_s"),
            _c_double(dv, "step"), _c_double(dv, "exp_tau_s")) == (-0.3, 1.5, 9.75, 0.0, 60.0)


@needs_arm
def test_cfggen_refuses_a_table_beyond_the_mcu_staging_capacity(tmp_path):
    """drive_sim holds 8192 table samples; the M4 build's staging buffer 4096 (pil.mk
    MCU_TABLE_MAX): a configuration asking for more is refused naming the key, nothing written."""
    code, err, c_text = _cfggen(tmp_path, "drive:\n  fs_hz: 2560\n  rec_capacity: 1000\n  table_capacity: 4097\n")
    assert code == 2 and c_text is None
    assert err.startswith("cfggen: error: ") and "drive.table_capacity = 4097" in err and "at most 4096" in err
    assert len(err.strip().splitlines()) == 1
