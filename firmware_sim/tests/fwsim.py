"""ctypes access to firmware_sim/build/libfwsim.so (drive core + simulated plant) for pytest
and the benchmarks. Parameter ids come from the generated od_params.h (configs/od.yaml).

    sim = FwSim("configs/plant_twomass.yaml")
    sim.set("KFC", 0.1); sim.enable(); sim.sine(amplitude=0.5, period=2560, cycles=1, ...)
    sim.start(); sim.run_until_idle(); rec = sim.record()   # (samples, signals) float32
"""
import ctypes
import os
import re
import subprocess

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
FW = os.path.dirname(HERE)
LIB_PATH = os.path.join(FW, "build", "libfwsim.so")
PARAMS_H = os.path.join(FW, "build", "gen", "od_params.h")

DRV_OK = 0
STATUS = ["OK", "NO_PARAM", "READ_ONLY", "NOT_FINITE", "RANGE_HIGH", "RANGE_LOW", "STATE",
          "NO_FIT", "LENGTH", "GENERAL", "INCOMPATIBLE", "VALUE", "TOO_LONG"]
SIG_BITS = {"reference": 0, "plant_input": 1, "motor_angle": 2, "load_angle": 3, "error": 4}


class FwError(RuntimeError):
    """A drive call returned a status other than DRV_OK."""


def _ensure_built():
    if not os.path.exists(LIB_PATH):
        subprocess.run(["make", "--no-print-directory", "-C", FW, "core-all"], check=True,
                       stdout=subprocess.DEVNULL)
    return LIB_PATH


def param_ids():
    """{name: (id, type)} from the generated od_params.h; type 'F32' or 'U32'."""
    _ensure_built()
    with open(PARAMS_H, encoding="utf-8") as f:
        text = f.read()
    enum = text[text.index("typedef enum {"):text.index("} drv_param_id_t;")]
    names = re.findall(r"DRV_P_(\w+),", enum)
    types = dict(re.findall(r"\[DRV_P_(\w+)\] = \{DRV_PT_(F32|U32)", text))
    return {n: (i, types[n]) for i, n in enumerate(names)}


def load_lib():
    lib = ctypes.CDLL(_ensure_built())
    vp, u32, f32, f64, u64 = ctypes.c_void_p, ctypes.c_uint32, ctypes.c_float, ctypes.c_double, ctypes.c_uint64
    sigs = {
        "sim_new_from_file": (vp, [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_size_t]),
        "sim_free": (None, [vp]),
        "sim_drv": (vp, [vp]),
        "sim_plant": (vp, [vp]),
        "sim_step": (f32, [vp]),
        "sim_run": (None, [vp, u64]),
        "sim_run_until_idle": (u64, [vp, u64]),
        "sim_get_f32": (ctypes.c_int, [vp, ctypes.c_int, ctypes.POINTER(f32)]),
        "drv_get_f32": (ctypes.c_int, [vp, ctypes.c_int, ctypes.POINTER(f32)]),
        "drv_set_f32": (ctypes.c_int, [vp, ctypes.c_int, f32]),
        "drv_get_u32": (ctypes.c_int, [vp, ctypes.c_int, ctypes.POINTER(u32)]),
        "drv_set_u32": (ctypes.c_int, [vp, ctypes.c_int, u32]),
        "drv_run_start": (ctypes.c_int, [vp]),
        "drv_enable": (None, [vp, ctypes.c_bool]),
        "drv_set_target": (ctypes.c_int, [vp, f32]),
        "drv_rec_size_bytes": (u32, [vp]),
        "drv_rec_read": (ctypes.c_int, [vp, u32, ctypes.c_char_p, u32]),
        "drv_stat_size_bytes": (u32, [vp]),
        "drv_stat_read": (ctypes.c_int, [vp, u32, ctypes.c_char_p, u32]),
        "drv_lines_write": (ctypes.c_int, [vp, u32, ctypes.c_char_p, u32]),
        "drv_lines_commit": (ctypes.c_int, [vp, u32]),
        "drv_line_stats_size_bytes": (u32, [vp]),
        "drv_line_stats_read": (ctypes.c_int, [vp, u32, ctypes.c_char_p, u32]),
        "drv_table_size_bytes": (u32, [vp]),
        "drv_table_read": (ctypes.c_int, [vp, u32, ctypes.c_char_p, u32]),
        "drv_table_write": (ctypes.c_int, [vp, u32, ctypes.c_char_p, u32]),
        "drv_table_commit": (ctypes.c_int, [vp, u32]),
        "plant_set_state": (None, [vp, f64, f64, f64, f64]),
        "plant_get_state": (None, [vp, ctypes.POINTER(f64)]),
        "plant_advance": (None, [vp, f64, f64]),
        "plant_mode": (ctypes.c_int, [vp]),
    }
    for name, (res, args) in sigs.items():
        fn = getattr(lib, name)
        fn.restype = res
        fn.argtypes = args
    return lib


class FwSim:
    """One simulated drive + plant from a configs/plant_*.yaml file."""

    _lib = None
    _ids = None

    def __init__(self, config_path):
        if FwSim._lib is None:
            FwSim._lib = load_lib()
            FwSim._ids = param_ids()
        self.lib, self.ids = FwSim._lib, FwSim._ids
        err = ctypes.create_string_buffer(512)
        self.sim = self.lib.sim_new_from_file(os.fsencode(config_path), err, len(err))
        if not self.sim:
            raise ValueError(err.value.decode())
        self.drv = self.lib.sim_drv(self.sim)
        self.plant = self.lib.sim_plant(self.sim)

    def close(self):
        if self.sim:
            self.lib.sim_free(self.sim)
            self.sim = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        self.close()

    def _check(self, st, what):
        if st != DRV_OK:
            raise FwError(f"{what}: DRV_E_{STATUS[st]}")

    def set(self, name, value):
        pid, typ = self.ids[name]
        if typ == "F32":
            st = self.lib.drv_set_f32(self.drv, pid, float(value))
        else:
            st = self.lib.drv_set_u32(self.drv, pid, int(value))
        self._check(st, f"set {name}={value}")

    def try_set(self, name, value):
        pid, typ = self.ids[name]
        if typ == "F32":
            return self.lib.drv_set_f32(self.drv, pid, float(value))
        return self.lib.drv_set_u32(self.drv, pid, int(value))

    def get(self, name):
        pid, typ = self.ids[name]
        if typ == "F32":
            v = ctypes.c_float()
            st = self.lib.drv_get_f32(self.drv, pid, ctypes.byref(v))
        else:
            v = ctypes.c_uint32()
            st = self.lib.drv_get_u32(self.drv, pid, ctypes.byref(v))
        self._check(st, f"get {name}")
        return v.value

    def truth(self, name):
        v = ctypes.c_float()
        self._check(self.lib.sim_get_f32(self.sim, self.ids[name][0], ctypes.byref(v)), f"sim {name}")
        return v.value

    def enable(self, on=True):
        self.lib.drv_enable(self.drv, bool(on))

    def configure(self, **params):
        for k, v in params.items():
            self.set(k.upper(), v)

    def start(self):
        self._check(self.lib.drv_run_start(self.drv), "run start")

    def run(self, steps):
        self.lib.sim_run(self.sim, int(steps))

    def run_until_idle(self, max_steps=10**9):
        return self.lib.sim_run_until_idle(self.sim, int(max_steps))

    def record(self):
        """Recorder contents as a (samples, n_signals) float32 array and the signal names."""
        mask = self.get("REC_SIGNALS")
        names = [n for n, b in SIG_BITS.items() if mask & (1 << b)]
        size = self.lib.drv_rec_size_bytes(self.drv)
        buf = ctypes.create_string_buffer(max(size, 1))
        self._check(self.lib.drv_rec_read(self.drv, 0, buf, size), "rec read")
        data = np.frombuffer(buf.raw[:size], dtype="<f4").reshape(-1, len(names))
        return data, names

    def stats_bytes(self):
        """The statistics data (object 0x2041) as bytes (fftune.analysis.stats.parse_stats)."""
        size = self.lib.drv_stat_size_bytes(self.drv)
        buf = ctypes.create_string_buffer(max(size, 1))
        self._check(self.lib.drv_stat_read(self.drv, 0, buf, size), "stat read")
        return buf.raw[:size]

    def set_lines(self, bins):
        """Write and commit the line list (object 0x2042: u16 LE bins)."""
        raw = np.asarray(bins, dtype="<u2").tobytes()
        self._check(self.lib.drv_lines_write(self.drv, 0, raw, len(raw)), "line list write")
        self._check(self.lib.drv_lines_commit(self.drv, len(raw)), "line list commit")

    def line_stats_bytes(self):
        """The line statistics data (object 0x2043) as bytes (parse_line_stats)."""
        size = self.lib.drv_line_stats_size_bytes(self.drv)
        buf = ctypes.create_string_buffer(max(size, 1))
        self._check(self.lib.drv_line_stats_read(self.drv, 0, buf, size), "line statistics read")
        return buf.raw[:size]

    def table(self):
        size = self.lib.drv_table_size_bytes(self.drv)
        buf = ctypes.create_string_buffer(max(size, 1))
        self._check(self.lib.drv_table_read(self.drv, 0, buf, size), "table read")
        return np.frombuffer(buf.raw[:size], dtype="<f4").copy()

    def plant_state(self):
        x = (ctypes.c_double * 4)()
        self.lib.plant_get_state(self.plant, x)
        return np.array(x[:])

    def plant_set_state(self, th1, w1, th2, w2):
        self.lib.plant_set_state(self.plant, th1, w1, th2, w2)

    def plant_advance(self, u, dt):
        self.lib.plant_advance(self.plant, float(u), float(dt))

    def plant_mode(self):
        return self.lib.plant_mode(self.plant)


def sine_response(config_path, kfc, amplitude, period, cycles=1, settle=3, record=4, **overrides):
    """Run a sine reference on the simulated drive; return the recorded motor angle
    (record * period samples) and the reference."""
    with FwSim(config_path) as sim:
        for k, v in overrides.items():
            sim.set(k.upper(), v)
        sim.set("KFC", kfc)
        sim.enable()
        sim.configure(exc_kind=1, exc_inject=0, exc_amplitude=amplitude, exc_period=period,
                      exc_sine_cycles=cycles, exc_settle_periods=settle, exc_record_periods=record,
                      rec_signals=0x1F)
        sim.start()
        sim.run_until_idle()
        data, names = sim.record()
    return {n: data[:, i].astype(np.float64) for i, n in enumerate(names)}


def odd_harmonic_ratios(y, period, cycles=1, record=1, orders=(3, 5, 7)):
    """|Y(k f0)| / |Y(f0)| for the odd orders, from an integer number of periods
    (leakage free). y holds record * period samples."""
    y = np.asarray(y, dtype=np.float64)
    Y = np.fft.rfft(y - y.mean())
    base = cycles * record
    return {k: abs(Y[k * base]) / abs(Y[base]) for k in orders}
