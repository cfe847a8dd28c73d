"""Benchmark: the drive on the Cortex-M4F (processor-in-the-loop build, firmware_sim/port/mcu).

- Instructions per drv_step on the M4 (arm-none-eabi-gcc -O2, fpv4-sp-d16): pil_bench.elf
  under qemu-system-arm -icount shift=0 (every instruction 1 ns of virtual time; SysTick
  counts it at 168 MHz, so instructions = ticks / 0.168, exact). drv_step: controller +
  generator + recorder of 3 signals, no plant, 4000 steps in a recording run, counted over
  the benchmark loop (bench_drive_steps: + the loop's call and feedback, ~9 instructions).
  With the harmonic statistics on (K = 8 of 3 signals, power of 1): drv_step timed alone per
  call, and the background (drv_background, called between steps) per step.
- Beside it the x86-64 counts by callgrind (build/bench_fw instr): the same loop
  (--toggle-collect=bench_fw_drive_steps, what the M4 figure counts) and drv_step alone
  (--toggle-collect=drv_step, what `make -C firmware_sim bench` and the docs quote).
- The PIL interrupt's work per step (sim_step: the double-precision plant in software
  floating point + drv_step), mean and worst, against the 65625 cycles of one 2560 Hz period.
- Flash and RAM of build/mcu/pil.elf (make pil).
- The SLCAN link (qemu's UART model moves one byte at a time): expedited SDO reads per
  second and the block-upload rate of a recording, through python-can's slcan interface
  and the host's DriveClient (wall clock: depends on the machine's load).
Instruction counts do not depend on the machine's load; they are not M4 cycles (the M4
needs about 1-1.3 cycles per instruction, more for loads, divisions and branches).
Skipped with the reason when qemu-system-arm or arm-none-eabi-gcc is missing.
"""
import os
import re
import shutil
import subprocess
import sys

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..")
FW = os.path.join(ROOT, "firmware_sim")
BUILD = os.path.join(FW, "build")
STEPS = 4000
TICKS_PER_INSTRUCTION = 0.168  # 168 MHz SysTick, 1 ns per instruction (icount shift=0)
WORKLOADS = (("drv_step_table_64", ["table", "64"]), ("drv_step_table_1024", ["table", "1024"]),
             ("drv_step_sine", ["sine"]))


def make(*targets):
    subprocess.run(["make", "--no-print-directory", "-C", FW, f"PYTHON={sys.executable}", *targets],
                   check=True, stdout=subprocess.DEVNULL)


def m4_counts():
    out = subprocess.run(["qemu-system-arm", "-M", "netduinoplus2", "-display", "none", "-nodefaults",
                          "-kernel", os.path.join(BUILD, "mcu", "pil_bench.elf"),
                          "-semihosting-config", "enable=on,target=native", "-icount", "shift=0",
                          "-serial", "stdio"], check=True, capture_output=True, text=True, timeout=300).stdout
    if "BENCH done" not in out or "error" in out or "WRAPPED" in out:
        raise SystemExit(f"bench_mcu: pil_bench.elf failed:\n{out}")
    res = {}
    for name, ticks, steps in re.findall(r"^BENCH (\S+) ticks (\d+) steps (\d+)", out, re.M):
        res[name] = int(ticks) / TICKS_PER_INSTRUCTION / int(steps)
    res["slow_steps"] = int(re.search(r"closed_loop_slow_steps (\d+)", out).group(1))
    res["lines_count"] = int(re.search(r"lines_count (\d+)", out).group(1))
    return res


def _callgrind(args, toggle):
    cg = os.path.join(BUILD, "callgrind.mcu.out")
    subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={cg}", f"--toggle-collect={toggle}",
                    os.path.join(BUILD, "bench_fw"), "instr", *args, str(STEPS)], check=True, capture_output=True)
    with open(cg) as f:
        text = f.read()
    return int(re.search(r"^(?:summary|totals):\s*(\d+)", text, re.M).group(1)) / STEPS


def x86_counts():
    """name -> (over the benchmark loop, drv_step alone) per step; for the statistics run
    (drv_step alone, background stat_process) per step."""
    if shutil.which("valgrind") is None:
        return {}
    res = {name: (_callgrind(args, "bench_fw_drive_steps"), _callgrind(args, "drv_step"))
           for name, args in WORKLOADS}
    res["stats"] = (_callgrind(["sine-stats"], "drv_step"), _callgrind(["sine-stats"], "stat_process"))
    return res


def sizes():
    out = subprocess.run(["make", "--no-print-directory", "-C", FW, f"PYTHON={sys.executable}", "pil"],
                         check=True, capture_output=True, text=True).stdout
    return re.search(r"^pil: .*$", out, re.M).group(0)


def link_rates():
    """SDO round trips and block-upload bytes per wall second over the SLCAN link."""
    import importlib.util
    import time

    sys.path.insert(0, os.path.join(ROOT, "tests"))
    from fftune.host.drive import BusOptions, DriveClient
    from fftune.host.odmap import DEFAULT_EDS
    spec = importlib.util.spec_from_file_location("pil_run", os.path.join(FW, "port", "mcu", "pil_run.py"))
    pil = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(pil)
    with pil.start() as target:
        with DriveClient(BusOptions(interface="slcan", channel=target.channel, eds=DEFAULT_EDS),
                         heartbeat_ms=500, progress=False) as c:
            c.enable()
            c.run({"exc_kind": 1, "exc_period": 2048, "exc_sine_cycles": 1, "exc_amplitude": 0.3,
                   "exc_settle_periods": 0, "exc_record_periods": 1, "exc_inject": 0})
            n = 100
            t0 = time.monotonic()
            for _ in range(n):
                c.read(0x1000, 0)
            sdo_per_s = n / (time.monotonic() - t0)
            t0 = time.monotonic()
            data = c.upload_recording()
            upload_s = time.monotonic() - t0
    return sdo_per_s, len(data), upload_s


def main():
    missing = [t for t in ("qemu-system-arm", "arm-none-eabi-gcc") if shutil.which(t) is None]
    if missing:
        print(f"bench_mcu: skipped: {', '.join(missing)} not installed (sudo make system-deps)")
        return 0
    make("core-all", "pil", "pil-bench")
    m4 = m4_counts()
    x86 = x86_counts()
    print(f"drv_step instructions per controller step (controller + generator + recorder of 3 signals, "
          f"no plant; {STEPS} steps), counted over the benchmark loop (drv_step + the loop's call and "
          f"feedback) on both; x86 drv_step alone as `make -C firmware_sim bench` prints it:")
    for name, _ in WORKLOADS:
        x = (f"{x86[name][0]:.0f} (drv_step alone {x86[name][1]:.0f})" if name in x86
             else "n/a (valgrind not installed)")
        print(f"  {name[9:]:>10}: Cortex-M4F (qemu -icount) {m4[name]:.0f}   x86-64 (callgrind) {x}")
    xs = (f"x86-64 (callgrind) {x86['stats'][0]:.0f}, background {x86['stats'][1]:.0f}" if "stats" in x86
          else "x86-64 n/a (valgrind not installed)")
    print(f"  sine with harmonic statistics (K = 8 of 3 signals, power of 1), drv_step timed alone per call, "
          f"drv_background between steps: Cortex-M4F {m4['drv_step_sine_stats']:.0f}, background "
          f"{m4['background_sine_stats']:.0f} per step;   {xs} per step")
    print(f"  line statistics, a later multisine period (shifted data, after the base period 0) of N = 1024 "
          f"through drv_background (3 real FFTs, "
          f"{m4['lines_count']} lines: the PIL build's LSTAT_LINES_MAX): Cortex-M4F {m4['lines_period_1024']:.0f} "
          f"instructions per period")
    period = 168e6 / 2560
    print(f"PIL control interrupt (sim_step: software-double plant + drv_step, sine run of 4096 steps): "
          f"mean {m4['closed_loop_total']:.0f}, worst {m4['closed_loop_worst']:.0f} instructions per step "
          f"({m4['slow_steps']} steps on the plant's RK4 event path); one 2560 Hz period = {period:.0f} cycles "
          f"at 168 MHz")
    print(sizes())
    sdo_per_s, nbytes, upload_s = link_rates()
    print(f"SLCAN link (qemu UART, python-can slcan, wall clock, machine load included): "
          f"{sdo_per_s:.0f} expedited SDO reads/s (2 frames each); block upload of {nbytes} bytes in "
          f"{upload_s:.2f} s = {nbytes / upload_s / 1024:.1f} KiB/s ({nbytes / 7 / upload_s:.0f} frames/s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
