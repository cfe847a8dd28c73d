"""``fftune analyze``: results, JSON keys and shapes, and every bad-input case (exit 2, one line)."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from fftune.analysis import capture
from fftune.analysis.multisine import multisine_realizations
from fftune.host.cli import main

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "tests" / "data" / "kul_motorbench_twomass.npz"   # MIT, see tests/data/
M, T, P, N, FS = 3, 1, 4, 256, 1000.0


def wiener_data(m=M, t=T, p=P, n=N, seed=0):
    designs = multisine_realizations(m, FS, n, k_min=1, k_max=100, seed=4, rms=0.5)
    u = np.repeat(np.stack([d.period for d in designs])[:, None, :], t + p, axis=1)
    rng = np.random.default_rng(seed)
    y = u + 0.2 * u ** 3 + 1e-4 * rng.standard_normal(u.shape)
    return u.reshape(-1), y.reshape(-1)


def write_csv(path, columns):
    names = list(columns)
    table = np.column_stack([columns[c] for c in names])
    with open(path, "w") as f:
        f.write(",".join(names) + "\n")
        np.savetxt(f, table, delimiter=",", fmt="%.17g")
    return path


def cli(capsys, *args):
    code = main(["analyze", *map(str, args)])
    out = capsys.readouterr()
    return code, out.out, out.err


BLA_ARGS = ("--fs", FS, "--period", N, "--realizations", M, "--settle-periods", T)


def test_bla_json_keys_and_shapes(tmp_path, capsys):
    u, y = wiener_data()
    f = write_csv(tmp_path / "d.csv", {"u": u, "y": y})
    out_json = tmp_path / "res.json"
    code, out, err = cli(capsys, "bla", f, *BLA_ARGS, "--json", out_json, "--plot", tmp_path / "fig")
    assert code == 0, err
    doc = json.loads(out_json.read_text())
    assert list(doc) == ["freq", "G", "var_total", "var_noise", "var_nl", "odd_nonexcited",
                         "even_nonexcited", "summary", "nonexcited", "verdict"]
    e = len(doc["freq"])
    assert e > 30 and all(len(g) == 2 for g in doc["G"]) and len(doc["G"]) == e
    for key in ("var_total", "var_noise", "var_nl"):
        assert len(doc[key]) == e
    for key in ("odd_nonexcited", "even_nonexcited"):
        assert len(doc[key]["freq"]) == len(doc[key]["level_db"]) > 0
    s = doc["summary"]
    assert s["realizations"] == M and s["periods"] == P and s["odd_detected"] is True
    assert s["even_detected"] is False
    # the numbers agree with the library on the same data
    from fftune.analysis.bla import robust_bla
    res = robust_bla(u.reshape(M, T + P, N), y.reshape(M, T + P, N), fs=FS, settle_periods=T)
    np.testing.assert_allclose(np.array(doc["G"])[:, 0], res.G.real, rtol=1e-12)
    np.testing.assert_allclose(doc["freq"], res.freq)
    assert "odd non-excited" in out
    assert (tmp_path / "fig" / "bla_output_spectrum.png").stat().st_size > 10000


def test_bla_single_realization_gives_null_nl_variance(tmp_path, capsys):
    u, y = wiener_data(m=1)
    f = tmp_path / "d.npz"
    np.savez(f, u=u, y=y, fs=np.float64(FS))
    out_json = tmp_path / "r.json"
    code, out, err = cli(capsys, "bla", f, "--period", N, "--skip-periods", T, "--json", out_json)
    assert code == 0, err
    doc = json.loads(out_json.read_text())
    assert doc["var_nl"] is None and doc["var_total"] is None and doc["var_noise"] is not None
    assert "M = 1" in out


def test_bla_single_period_gives_null_noise_variance(tmp_path, capsys):
    u, y = wiener_data(t=0, p=1)
    f = tmp_path / "d.mat"
    scipy.io.savemat(f, {"u": u, "y": y})
    out_json = tmp_path / "r.json"
    code, out, err = cli(capsys, "bla", f, "--fs", FS, "--period", N, "--realizations", M,
                         "--json", out_json)
    assert code == 0, err
    doc = json.loads(out_json.read_text())
    assert doc["var_noise"] is None and doc["var_nl"] is None and len(doc["var_total"]) > 0
    assert "P = 1" in out


def test_bla_known_reference_columns_and_lines_file(tmp_path, capsys):
    u, y = wiener_data()
    f = write_csv(tmp_path / "d.csv", {"cmd": u, "current": u * 1.0, "angle": y})
    designs = multisine_realizations(1, FS, N, k_min=1, k_max=100, seed=4)
    lines = tmp_path / "lines.txt"
    lines.write_text("\n".join(str(k) for k in designs[0].excited))
    out_json = tmp_path / "r.json"
    code, out, err = cli(capsys, "bla", f, *BLA_ARGS, "--columns", "u=current,y=angle,r=cmd",
                         "--lines", lines, "--json", out_json)
    assert code == 0, err
    doc = json.loads(out_json.read_text())
    assert doc["summary"]["known_reference"] is True
    np.testing.assert_allclose(doc["freq"], designs[0].excited * FS / N)
    assert "known reference" in out


def test_bla_from_capture_file(tmp_path, capsys):
    u, y = wiener_data(m=1, t=0, p=3)
    path = capture.write_run(tmp_path / "run.h5",
                             {"reference": u, "plant_input": u, "motor_angle": y},
                             {"fs_hz": FS, "n_period": N, "settle_periods": 0,
                              "record_periods": 3, "experiment": "multisine"})
    out_json = tmp_path / "r.json"
    code, out, err = cli(capsys, "bla", path, "--json", out_json)
    assert code == 0, err
    doc = json.loads(out_json.read_text())
    assert doc["summary"]["known_reference"] is True and doc["summary"]["periods"] == 3


def test_bla_from_capture_directory(tmp_path, capsys):
    u, y = wiener_data(m=M, t=T, p=P)
    u, y = u.reshape(M, -1), y.reshape(M, -1)
    runs = tmp_path / "runs"
    runs.mkdir()
    for m in range(M):
        capture.write_run(runs / f"detect-M{m:02d}.h5", {"plant_input": u[m], "motor_angle": y[m]},
                          {"fs_hz": FS, "n_period": N, "settle_periods": T, "record_periods": P,
                           "experiment": "multisine", "realization": m})
    out_json = tmp_path / "r.json"
    code, out, err = cli(capsys, "bla", runs, "--json", out_json)
    assert code == 0, err
    doc = json.loads(out_json.read_text())
    s = doc["summary"]
    assert (s["realizations"], s["periods"], s["settle_periods"]) == (M, P, T)
    assert s["known_reference"] is False and len(doc["var_nl"]) == len(doc["freq"])
    capture.write_run(runs / "other.h5", {"plant_input": u[0], "motor_angle": y[0]},
                      {"fs_hz": FS, "n_period": N, "settle_periods": T, "record_periods": P,
                       "experiment": "multisine", "realization": 0, "level_index": 1})
    code, out, err = cli(capsys, "bla", runs)
    assert code == 2 and "several levels" in err
    # the host's captures/ mixes levels and experiments: --experiment/--level pick one set
    code, out, err = cli(capsys, "bla", runs, "--experiment", "multisine", "--level", "1")
    assert code == 0, err
    assert "M = 1" in out
    code, out, err = cli(capsys, "bla", runs, "--experiment", "tune")
    assert code == 2 and "no capture run of experiment 'tune'" in err
    code, out, err = cli(capsys, "bla", runs / "other.h5", "--level", "0")
    assert code == 2 and "not in a single file" in err


def sine_data(repeats=3, p=4, n=512, k0=8, amplitude=1.5):
    t = np.arange(repeats * p * n)
    u = amplitude * np.sin(2 * np.pi * k0 * t / n)
    rng = np.random.default_rng(0)
    y = np.clip(u, -1, 1) + 1e-4 * rng.standard_normal(u.size)
    return u, y


def test_hosidf_json_keys_and_values(tmp_path, capsys):
    u, y = sine_data()
    f = write_csv(tmp_path / "s.csv", {"u": u, "y": y})
    out_json = tmp_path / "h.json"
    code, out, err = cli(capsys, "hosidf", f, "--fs", 512.0, "--period", 512, "--realizations", 3,
                         "--harmonics", 5, "--json", out_json, "--plot", tmp_path / "p")
    assert code == 0, err
    doc = json.loads(out_json.read_text())
    assert list(doc) == ["f0", "amplitude", "H", "H_std"]
    assert doc["f0"] == pytest.approx(8.0) and doc["amplitude"] == pytest.approx(1.5, rel=1e-9)
    assert len(doc["H"]) == 5 and all(len(h) == 2 for h in doc["H"]) and len(doc["H_std"]) == 5
    beta = np.arcsin(1 / 1.5)
    h1 = 2 / np.pi * (beta + np.sin(beta) * np.cos(beta))
    assert doc["H"][0][0] == pytest.approx(h1, rel=1e-3)
    assert abs(doc["H"][1][0]) < 1e-3                      # even harmonic ~ 0
    assert (tmp_path / "p" / "hosidf_harmonics.png").exists()
    code, out, err = cli(capsys, "hosidf", f, "--fs", 512.0, "--period", 512, "--json", out_json)
    assert code == 0 and json.loads(out_json.read_text())["H_std"] == [None] * 7


BAD_CASES = {
    "wrong_length": (["--fs", FS, "--period", N, "--realizations", M, "--periods", 9],
                     "wrong length"),
    "period_does_not_divide": (["--fs", FS, "--period", 300], "does not divide"),
    "missing_column": (["--fs", FS, "--period", N, "--columns", "u=u,y=nope"], "no column"),
    "bad_columns_syntax": (["--fs", FS, "--period", N, "--columns", "u:u"], "ROLE=NAME"),
    "no_fs": (["--period", N], "--fs"),
    "no_period": (["--fs", FS], "--period"),
    "zero_input_power": (["--fs", FS, "--period", N, "--realizations", M, "--lines", "LINES"],
                         "zero power"),
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bla_bad_input_exit_2_one_line_no_output(tmp_path, capsys, case):
    u, y = wiener_data()
    f = write_csv(tmp_path / "d.csv", {"u": u, "y": y})
    args, expected = BAD_CASES[case]
    lines = tmp_path / "lines.txt"
    lines.write_text("2\n4\n")                        # even bins: no input power there
    args = [str(lines) if a == "LINES" else a for a in args]
    out_json = tmp_path / "out.json"
    code, out, err = cli(capsys, "bla", f, *args, "--json", out_json)
    assert code == 2
    assert err.startswith("fftune: error: ") and err.count("\n") == 1 and expected in err
    assert "Traceback" not in err
    assert sorted(tmp_path.iterdir()) == sorted([f, lines])       # nothing written


@pytest.mark.parametrize("content,expected", [
    ("u,y\n1,2\n3,x\n", "line 3, column 'y'"),
    ("u,y\n1,2\nnan,4\n", "NaN or inf"),
    ("u,y\n1,2\n3\n", "line 3"),
    ("u\n1\n2\n", "no column/signal 'y'"),
])
def test_bad_csv_contents(tmp_path, capsys, content, expected):
    f = tmp_path / "d.csv"
    f.write_text(content)
    code, out, err = cli(capsys, "bla", f, "--fs", 10, "--period", 4, "--json", tmp_path / "o.json")
    assert code == 2 and expected in err and err.count("\n") == 1
    assert not (tmp_path / "o.json").exists()


def test_hosidf_sine_off_grid_rejected(tmp_path, capsys):
    t = np.arange(2048)
    u = np.sin(2 * np.pi * 8.4 * t / 512)
    f = write_csv(tmp_path / "s.csv", {"u": u, "y": u ** 3})
    code, out, err = cli(capsys, "hosidf", f, "--fs", 512.0, "--period", 512,
                         "--json", tmp_path / "h.json")
    assert code == 2 and "off the DFT grid" in err and not (tmp_path / "h.json").exists()


def test_existing_json_is_replaced_only_on_success(tmp_path, capsys):
    u, y = wiener_data()
    f = write_csv(tmp_path / "d.csv", {"u": u, "y": y})
    out_json = tmp_path / "r.json"
    out_json.write_text("previous")
    code, _, _ = cli(capsys, "bla", f, "--fs", FS, "--period", 300, "--json", out_json)
    assert code == 2 and out_json.read_text() == "previous"
    code, _, _ = cli(capsys, "bla", f, *BLA_ARGS, "--json", out_json)
    assert code == 0 and json.loads(out_json.read_text())["freq"]


def test_console_script_subprocess(tmp_path):
    u, y = wiener_data()
    f = write_csv(tmp_path / "d.csv", {"u": u, "y": y})
    exe = Path(sys.executable).parent / "fftune"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "fftune.host.cli"]
    ok = subprocess.run(cmd + ["analyze", "bla", str(f), "--fs", str(FS), "--period", str(N),
                               "--realizations", str(M), "--settle-periods", "1"],
                        capture_output=True, text=True)
    assert ok.returncode == 0 and "BLA of y / u" in ok.stdout
    bad = subprocess.run(cmd + ["analyze", "bla", str(tmp_path / "missing.csv"), "--fs", "1",
                                "--period", "8"], capture_output=True, text=True)
    assert bad.returncode == 2 and "no such file" in bad.stderr and "Traceback" not in bad.stderr


def test_real_data_through_the_cli(tmp_path, capsys):
    d = np.load(DATA)
    f = tmp_path / "b.npz"
    np.savez(f, iq=d["B_iq"].astype(float).reshape(-1),
             theta=d["B_theta_motor"].astype(float).reshape(-1), fs=d["fs"])
    out_json = tmp_path / "b.json"
    code, out, err = cli(capsys, "bla", f, "--period", 2500, "--skip-periods", 1,
                         "--columns", "u=iq,y=theta", "--json", out_json)
    assert code == 0, err
    doc = json.loads(out_json.read_text())
    assert len(doc["freq"]) == 60 and doc["var_nl"] is None
    assert doc["summary"]["odd_re_even_db"] == pytest.approx(3.3, abs=1.0)
