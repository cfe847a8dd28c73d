"""Shared by the processor-in-the-loop tests (tests/test_mcu_*.py): build the M4 ELF for
configs/pil.yaml and start it in qemu-system-arm (firmware_sim/port/mcu/pil_run.py)."""
import importlib.util
import os
import shutil
import subprocess
import sys

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir))
FW = os.path.join(REPO, "firmware_sim")
MCU_BUILD = os.path.join(FW, "build", "mcu")
PIL_CONFIG = os.path.join(REPO, "configs", "pil.yaml")
PIL_PLANT = os.path.join(MCU_BUILD, "plant.yaml")  # what the ELF has compiled in
ELF = os.path.join(MCU_BUILD, "pil.elf")


def pil_missing_reason():
    """Why the M4 tests cannot run here, or None."""
    for tool, pkg in (("qemu-system-arm", "qemu-system-arm"), ("arm-none-eabi-gcc", "gcc-arm-none-eabi")):
        if shutil.which(tool) is None:
            return f"{tool} not installed (package {pkg}: sudo make system-deps)"
    return None


def build_pil():
    """make -C firmware_sim pil (the ELF for configs/pil.yaml); returns make's output."""
    r = subprocess.run(["make", "--no-print-directory", "-C", FW, f"PYTHON={sys.executable}", "pil"],
                       capture_output=True, text=True)
    if r.returncode != 0:
        raise AssertionError(f"make pil failed:\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}")
    return r.stdout


def pil_run_module():
    spec = importlib.util.spec_from_file_location("pil_run", os.path.join(FW, "port", "mcu", "pil_run.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def symbol_address(name, elf=ELF):
    """Address of a global symbol of the ELF (arm-none-eabi-nm)."""
    out = subprocess.run(["arm-none-eabi-nm", elf], capture_output=True, text=True, check=True).stdout
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[2] == name:
            return int(parts[0], 16)
    raise AssertionError(f"{name} not in {elf}")
