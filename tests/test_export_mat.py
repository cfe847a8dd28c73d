"""``.mat`` export: one struct per capture, every number a double, valid MATLAB names,
units and fs; read back by scipy.io.loadmat and, when installed, by GNU Octave."""
import json
import shutil
import subprocess

import numpy as np
import pytest
import scipy.io

from fftune.analysis import capture
from fftune.host.cli import main

FS, N, T, P = 2560.0, 1024, 1, 2      # fs_hz / n_period = 2.5: integer division would give 3


def meta(**kw):
    m = {"fs_hz": FS, "n_period": N, "settle_periods": T, "record_periods": P,
         "experiment": "sine", "level_index": 3, "realization": 1,
         "parameters": {"kfc": 0.25, "exc_period": N, "ms_seed": 7, "rec_signals": 31,
                        "2nd-gain": 1.5, "end": 2},
         "firmware_version": "fw 1.2.3", "started_at": "2026-01-01T00:00:00+00:00",
         "metadata": {"operator": "test", "nested": [1, 2]}}
    m.update(kw)
    return m


def write(tmp_path, name="detect-L03-M01.h5", extra_signal=False):
    rng = np.random.default_rng(0)
    sig = {k: rng.standard_normal((T + P) * N) for k in capture.STANDARD_SIGNALS}
    if extra_signal:
        sig["current_q"] = rng.standard_normal((T + P) * N)
    return capture.write_run(tmp_path / name, sig, meta()), sig


def numeric_leaves(value, where=""):
    """(path, ndarray) of every numeric leaf of a loadmat(simplify_cells=True) tree."""
    if isinstance(value, dict):
        for k, v in value.items():
            yield from numeric_leaves(v, f"{where}.{k}")
    elif not isinstance(value, str) and np.asarray(value).dtype.kind not in "US":
        yield where, np.asarray(value)             # (an empty text comes back as array)


def test_mat_struct_doubles_units_and_names(tmp_path):
    path, sig = write(tmp_path, extra_signal=True)
    mat = capture.export_mat(path, tmp_path / "detect-L03-M01.mat")
    content = {k: v for k, v in scipy.io.loadmat(mat, simplify_cells=True).items()
               if not k.startswith("__")}
    assert list(content) == ["detect_L03_M01"]            # one struct, a valid MATLAB name
    c = content["detect_L03_M01"]
    leaves = dict(numeric_leaves(c))
    assert leaves, "no numeric field"
    not_double = {k: v.dtype for k, v in leaves.items() if v.dtype != np.float64}
    assert not not_double, f"numeric fields not double: {not_double}"
    assert c["fs_hz"] == FS and c["n_period"] == N and c["fs_hz"] / c["n_period"] == 2.5
    assert (c["settle_periods"], c["record_periods"], c["level_index"], c["realization"]) == \
        (T, P, 3, 1)
    assert c["units"]["fs_hz"] == "Hz" and c["units"]["motor_angle"] == "rad"
    assert c["units"]["plant_input"] == "V" and np.size(c["units"]["current_q"]) == 0
    assert set(c["signals"]) == set(sig)
    for name, values in sig.items():
        np.testing.assert_array_equal(c["signals"][name], values.astype(np.float32))
    # parameter names that are not MATLAB identifiers are renamed, values kept
    params = c["parameters"]
    assert params["kfc"] == 0.25 and params["exc_period"] == N
    assert params["x2nd_gain"] == 1.5 and params["x_end"] == 2
    for name in [*c, *params, *c["signals"], *c["units"]]:
        assert capture.matlab_name(name) == name and len(name) <= 63, name
    assert json.loads(c["metadata_json"]) == {"operator": "test", "nested": [1, 2]}
    assert c["experiment"] == "sine"


def test_matlab_name_edge_cases():
    assert capture.matlab_name("a" * 80) == "a" * 63
    assert capture.matlab_name("") == "x"
    assert capture.matlab_name("_x") == "x_x"
    assert capture.matlab_name("for") == "x_for"
    assert capture.matlab_name("ok_name1") == "ok_name1"


def test_export_cli_writes_one_struct_per_capture(tmp_path, capsys):
    src = tmp_path / "captures"
    src.mkdir()
    write(src, "detect-L00-M00.h5")
    write(src, "detect-L00-M01.h5")
    assert main(["export", str(src), "--format", "mat", "--to", str(tmp_path / "mat")]) == 0
    files = sorted((tmp_path / "mat").glob("*.mat"))
    assert [f.name for f in files] == ["detect-L00-M00.mat", "detect-L00-M01.mat"]
    for f in files:
        names = [k for k in scipy.io.loadmat(f) if not k.startswith("__")]
        assert names == [f.stem.replace("-", "_")]


OCTAVE = shutil.which("octave-cli") or shutil.which("octave")


@pytest.mark.skipif(OCTAVE is None, reason="GNU Octave not installed (make system-deps adds it)")
def test_octave_reads_the_export_with_double_arithmetic(tmp_path):
    path, sig = write(tmp_path)
    mat = capture.export_mat(path, tmp_path / "run.mat")
    script = (f"s = load('{mat}'); c = s.run; "
              "printf('ratio=%.6f\\n', c.fs_hz / c.n_period); "
              "printf('class=%s,%s\\n', class(c.n_period), class(c.signals.motor_angle)); "
              "printf('size=%d,%d\\n', size(c.signals.motor_angle)); "
              "printf('unit=%s\\n', c.units.motor_angle); "
              "printf('kfc=%.4f\\n', c.parameters.kfc); "
              "printf('exp=%s\\n', c.experiment);")
    out = subprocess.run([OCTAVE, "--no-gui", "--norc", "--quiet", "--eval", script],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    lines = dict(line.split("=", 1) for line in out.stdout.split() if "=" in line)
    assert float(lines["ratio"]) == 2.5
    assert lines["class"] == "double,double"
    assert lines["size"] == f"{(T + P) * N},1"
    assert lines["unit"] == "rad" and lines["kfc"] == "0.2500" and lines["exp"] == "sine"
