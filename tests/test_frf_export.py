"""The BLA with its variances as .mat (analysis/frf_export.py, `fftune export --bla`): the
layout MATLAB's frd/idfrd and FdiTools take, read back by scipy and, when installed, by GNU
Octave as an FRF with its covariance; python-control's frequency_response on to_frd()."""
import shutil
import subprocess

import numpy as np
import pytest
import scipy.io

from fftune.analysis import frf_export
from fftune.analysis.bla import robust_bla
from fftune.analysis.multisine import multisine_realizations
from fftune.host.cli import main
from fftune.host.pipeline import run_pipeline
from host_fixtures import FakeDriveForTests
from test_host_experiments import _cfg

F = np.array([1.5, 2.5, 4.0, 7.25])
G = np.array([2 - 1j, -0.5 + 3j, 0.25j, -1.5 - 0.75j])
V = np.array([0.01, 0.04, 0.002, 0.3])
VN = np.array([0.004, 0.01, 0.001, 0.1])
VNL = np.array([0.03, -0.01, 0.005, 0.6])


def test_layout_for_matlab_fditools_and_plain(tmp_path):
    c = frf_export.frf_mat_content(F, G, V, VN, VNL, fs=2560.0, n_period=1024,
                                   input_unit="V", output_unit="rad")
    path = frf_export.export_frf_mat(tmp_path / "x.mat", c)
    d = scipy.io.loadmat(path)
    assert d["ResponseData"].shape == (1, 1, 4) and np.allclose(d["ResponseData"][0, 0], G)
    assert np.allclose(d["Frequency"][:, 0], 2 * np.pi * F) and d["Ts"][0, 0] == 0.0
    cov = d["CovarianceData"]
    assert cov.shape == (1, 1, 4, 2, 2)
    assert np.allclose(cov[0, 0, :, 0, 0], V / 2) and np.allclose(cov[0, 0, :, 1, 1], V / 2)
    assert np.all(cov[0, 0, :, 0, 1] == 0) and np.all(cov[0, 0, :, 1, 0] == 0)
    # FdiTools: the FRF as X = 1, Y = G, per-part variances
    assert np.allclose(d["freq"][:, 0], F) and np.allclose(d["Y"][:, 0], G) and np.all(d["X"] == 1)
    assert np.allclose(d["sY2"][:, 0], V / 2) and not d["sX2"].any() and not d["cXY"].any()
    gbla = d["Gbla"]
    assert gbla.shape == (4, 4) and np.allclose(gbla[0], G) and np.allclose(gbla[1].real, np.sqrt(V))
    assert np.allclose(gbla[2].real, np.sqrt(VN)) and np.allclose(gbla[3].real, np.sqrt([0.03, 0, 0.005, 0.6]))
    assert np.allclose(d["varG"][:, 0], V) and np.allclose(d["varG_nl"][:, 0], VNL)
    assert d["fs"][0, 0] == 2560.0 and d["input_unit"][0] == "V"
    with pytest.raises(Exception, match="increasing"):
        frf_export.frf_mat_content(F[::-1], G)
    with pytest.raises(Exception, match="var_total has 3"):
        frf_export.frf_mat_content(F, G, V[:3])
    with pytest.raises(FileExistsError):
        frf_export.export_frf_mat(tmp_path / "x.mat", c)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("bla")
    cfg = _cfg()
    cfg["quantify"]["enabled"] = cfg["tune"]["enabled"] = False
    d = FakeDriveForTests(fc_volt=0.3, fv_volt=0.02, noise_std=1e-4)
    d.enable()
    data = {}
    run_pipeline(d, cfg, str(root / "run"), log=lambda s: None, figures=False, data=data)
    assert main(["export", "--bla", str(root / "run"), "--to", str(root / "mat")]) == 0
    return root, data["detect_levels"]


def test_export_bla_command_writes_each_level(exported, capsys):
    root, levels = exported
    files = sorted((root / "mat").glob("bla-L*.mat"))
    assert [f.name for f in files] == ["bla-L01.mat", "bla-L02.mat"]
    for f, res in zip(files, levels.results):
        d = scipy.io.loadmat(f)
        assert np.allclose(d["G"][:, 0], res.G) and np.allclose(d["varG"][:, 0], res.var_total)
        assert d["input_unit"][0] == "V" and d["output_unit"][0] == "rad"
    # never overwritten: one error line
    assert main(["export", "--bla", str(root / "run"), "--to", str(root / "mat")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bla-L01.mat: exists" in err[0]


def test_export_bla_without_detect_captures_is_one_line(tmp_path, capsys):
    assert main(["export", "--bla", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"fftune: error: {tmp_path}: no capture files (captures/*.h5, *.stats.json)"]


@pytest.mark.skipif(shutil.which("octave") is None,
                    reason="GNU Octave not installed (make system-deps installs octave and octave-control)")
def test_octave_loads_the_frf_with_its_covariance(exported):
    root, levels = exported
    res = levels.results[-1]
    script = ("d = load('bla-L02.mat'); printf('%d %d %d\\n', size(d.ResponseData)); "
              "printf('%d %d %d %d %d\\n', size(d.CovarianceData)); printf('%d\\n', iscomplex(d.ResponseData)); "
              "printf('%.17g %.17g %.17g\\n', real(d.ResponseData(1,1,3)), imag(d.ResponseData(1,1,3)), "
              "2 * d.CovarianceData(1,1,3,2,2)); "
              "if isempty(pkg('list', 'control')) printf('nocontrol\\n'); else pkg load control; "
              "sys = frd(d.ResponseData, d.Frequency); [H, w] = frdata(sys); "
              "printf('frd %d %.17g %.17g\\n', numel(w), real(H(1,1,3)), w(3)); end")
    out = subprocess.run(["octave", "--no-gui", "--quiet", "--no-window-system", "--eval", script],
                         cwd=root / "mat", capture_output=True, text=True, timeout=120).stdout.split("\n")
    F = res.freq.size
    assert out[0] == f"1 1 {F}" and out[1] == f"1 1 {F} 2 2" and out[2] == "1"
    re_, im_, var = (float(x) for x in out[3].split())
    assert re_ == res.G[2].real and im_ == res.G[2].imag and var == pytest.approx(res.var_total[2], rel=1e-15)
    if out[4] != "nocontrol":           # the control package: an FRD model
        n, h, w = out[4].split()[1:]
        assert int(n) == F and float(h) == res.G[2].real and float(w) == pytest.approx(2 * np.pi * res.freq[2])


def test_python_control_frequency_response_on_the_frd():
    control = pytest.importorskip("control", reason="python-control is optional and not "
                                                    "installed here (pip install control)")
    designs = multisine_realizations(3, 100.0, 256, k_min=1, k_max=40, seed=4)
    u = np.repeat(np.stack([x.period for x in designs])[:, None], 2, 1)
    rng = np.random.default_rng(2)
    y = np.tanh(u) + 0.2 * u + 1e-3 * rng.standard_normal(u.shape)
    res = robust_bla(u, y, fs=100.0)
    frd = res.to_frd()
    resp = control.frequency_response(frd)
    assert np.allclose(resp.omega, 2 * np.pi * res.freq)
    assert np.allclose(np.squeeze(resp.magnitude), abs(res.G))
    assert np.array_equal(frd.var_total, res.var_total) and np.array_equal(frd.var_noise, res.var_noise)
