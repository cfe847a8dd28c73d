"""The firmware core + simulated plant (firmware_sim/build/libfwsim.so, via fwsim.py) behind
the :class:`fftune.host.drive.DriveClient` interface the experiments use, without CANopen.

The same C code as ``drive_sim`` (drive core, controller, excitation, recorder, plant), one
instance per drive so the plant state and the noise generator carry over between runs as
on drive_sim; only the CANopen transport is left out. It makes matrices of closed-loop
experiments (tests/bench/bench_tune.py) cheap; the product path through CANopen is
exercised by `make demo` and the drive_sim tests.
"""
import os
import sys
import tempfile
import time

import numpy as np

from fftune.analysis.errors import FftuneError
from fftune.host.drive import RunRecord
from fftune.host.odmap import PARAMS, SIGNAL_BITS

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir))
sys.path.insert(0, os.path.join(REPO, "firmware_sim", "tests"))

from fwsim import FwError, FwSim  # noqa: E402

PLANT_TWOMASS = os.path.join(REPO, "configs", "plant_twomass.yaml")


def plant_file(overrides, base=PLANT_TWOMASS, directory=None):
    """A plant YAML: ``base`` with ``overrides`` ({section: {key: number}}) applied."""
    from fftune.host.sim import derived_plant
    directory = directory or tempfile.mkdtemp(prefix="fftune-plant-")
    os.makedirs(directory, exist_ok=True)
    return derived_plant(base, overrides, os.path.join(directory, "plant.yaml"))


class FwSimDrive:
    """DriveClient-like access to one simulated drive (no CANopen)."""

    def __init__(self, plant_path):
        self.sim = FwSim(plant_path)
        self.runs = 0
        self.plant_path = plant_path

    def close(self):
        self.sim.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def identity(self):
        return {"vendor_id": 0xFF7, "product_code": 1, "revision": 0x10000, "serial": 0,
                "firmware_version": "libfwsim", "device_name": "fftune drive core (ctypes)",
                "node_id": 1, "bus": "none (ctypes)"}

    def plant_truth(self):
        return {a: float(self.sim.truth(a.upper())) for a in
                ("sim_fc_volt", "sim_fv_volt", "sim_fs_volt", "sim_noise_std", "sim_fc_torque")}

    def enable(self):
        self.sim.enable()

    def get(self, name):
        return self.sim.get(name.upper())

    def set(self, name, value):
        try:
            self.sim.set(name.upper(), value)
        except FwError as exc:
            raise FftuneError(f"writing {value!r} to '{name}': {exc}") from None
        except KeyError:
            raise FftuneError(f"no object named '{name}'") from None

    def set_parameters(self, values):
        for k, v in values.items():
            self.set(k, v)

    def read_parameters(self):
        out = {}
        for alias, e in PARAMS.items():
            if alias.startswith(("sim_", "meas_")) or e.access == "wo" or alias.upper() not in self.sim.ids:
                continue
            try:
                out[alias] = self.sim.get(alias.upper())
            except FwError:
                continue
        return out

    def run(self, parameters, signals=("reference", "plant_input", "motor_angle", "error"), desc="run",
            capture="raw", stats=None, lines=None):
        """As :meth:`fftune.host.drive.DriveClient.run` (capture 'raw', 'stats' or 'both';
        ``lines``: the multisine line statistics)."""
        from fftune.analysis.stats import parse_line_stats, parse_stats
        from fftune.host.drive import stats_parameters
        want_lines = lines is not None and capture != "raw"
        mask = 0
        if capture != "stats":
            for s in signals:
                mask |= 1 << SIGNAL_BITS[s]
        names = [n for n, b in sorted(SIGNAL_BITS.items(), key=lambda kv: kv[1]) if mask >> b & 1]
        if want_lines:
            mask |= 0x07
        self.set_parameters(dict(parameters, rec_signals=mask))
        self.set_parameters(stats_parameters(stats) if capture != "raw" and stats else
                            {"stat_harmonics": 0, "stat_signals": 0, "stat_power": 0})
        if want_lines:
            self.sim.set_lines(lines)
        if want_lines or "stat_line_mode" not in parameters:
            self.set("stat_line_mode", 1 if want_lines else 0)
        t0 = time.time()
        self.sim.start()
        self.sim.run_until_idle()
        self.runs += 1
        n = int(self.sim.get("EXC_PERIOD"))
        rec = int(self.sim.get("EXC_RECORD_PERIODS"))
        sig = {}
        if capture != "stats":
            data, rec_names = self.sim.record()
            sig = {name: data[:, i].astype(np.float64) for i, name in enumerate(rec_names) if name in names}
        run_stats = parse_stats(self.sim.stats_bytes()) if capture != "raw" and not want_lines else None
        run_lines = parse_line_stats(self.sim.line_stats_bytes()) if want_lines else None
        if run_lines is not None:
            run_lines.saturated_samples = int(self.sim.get("STAT_LINE_SATURATED"))
        return RunRecord(signals=sig, parameters=self.read_parameters(), fs_hz=float(self.sim.get("FS")),
                         period_samples=n, settle_periods=int(self.sim.get("EXC_SETTLE_PERIODS")),
                         record_periods=rec, run_counter=self.runs, t_start=t0, t_end=time.time(),
                         stats=run_stats, line_stats=run_lines)
