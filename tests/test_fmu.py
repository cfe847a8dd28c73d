"""FMU plants (docs/fmu.md): drive_sim co-simulating an FMI 2.0 co-simulation FMU.

- FMPy (the reference) and drive_sim simulate the same FMU open-loop to the same samples;
- an FMU built by FMPy's own tooling (fmpy.build, cmake) from C sources runs through
  `fftune demo --plant` unchanged (a law the project does not ship: tanh-smoothed Coulomb);
- every bad FMU (missing file, missing variable, wrong causality, a step that fails, a binary
  for another platform, an unsupported version, an unloadable binary) is one
  `fftune: error:` line naming the plant file and the variable or function, before the
  drive is enabled; a step that fails mid-run disables the drive;
- the plant file's keys, a machine axis with an FMU plant, sim.overrides' note.
"""
import os
import shutil
import sys
import zipfile

import numpy as np
import pytest
import yaml

from fftune.analysis.errors import FftuneError
from fftune.host.cli import main
from host_fixtures import EDS, REPO, drive_sim_missing_reason

FMU_BUILD = os.path.join(REPO, "firmware_sim", "build", "fmu")
LUGRE = os.path.join(FMU_BUILD, "lugre.fmu")
FS = 2560.0
LUGRE_PARAMS = {"Fc": 5.2e-3, "Fs": 7.5e-3, "vs": 0.15, "sigma0": 25.0, "sigma1": 0.015, "sigma2": 2.0e-4}

pytestmark = [
    pytest.mark.skipif(not os.path.exists(LUGRE), reason=f"{LUGRE} not built (make -C firmware_sim fmu)"),
    pytest.mark.skipif(drive_sim_missing_reason() is not None, reason=drive_sim_missing_reason() or ""),
]


@pytest.fixture(autouse=True)
def _fmu_cache(tmp_path_factory, monkeypatch):
    """FMUs unpack into a per-session cache (not the user's ~/.cache)."""
    monkeypatch.setenv("FFTUNE_FMU_CACHE", str(tmp_path_factory.getbasetemp() / "fmu-cache"))


def plant_file(tmp_path, fmu=LUGRE, name="plant.yaml", **fmu_keys):
    f = {"path": fmu, "input": "u", "output": "theta1", "parameters": dict(LUGRE_PARAMS)}
    f.update(fmu_keys)
    data = {"fmu": {k: v for k, v in f.items() if v is not None},
            "sensor": {"counts_per_rev": 0, "noise_std": 0.0, "seed": 1},
            "truth": {"kfc_v": 0.104},
            "controller": {"kp": 0.0, "kd": 0.0}}
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return str(path)


# ---- FMPy vs drive_sim, open loop ----

def test_fmpy_and_drive_sim_simulate_the_same_fmu_to_the_same_samples(tmp_path):
    from fmpy import simulate_fmu

    from fftune.host.drive import BusOptions, DriveClient
    from fftune.host.sim import start_drive_sim

    plant = plant_file(tmp_path)
    n = 2048
    req = {"exc_kind": 3, "exc_inject": 1, "exc_amplitude": 0.5, "exc_offset": 0.07, "exc_period": n,
           "ms_k_min": 1, "ms_k_max": 200, "ms_group": 0, "ms_seed": 11, "ms_realization": 0,
           "exc_settle_periods": 0, "exc_record_periods": 1}
    sim = start_drive_sim(plant, log_path=str(tmp_path / "drive_sim.log"))
    try:
        with DriveClient(BusOptions(port=sim.port, host=sim.host, eds=EDS), progress=False) as d:
            truth = d.plant_truth()
            d.enable()
            rec = d.run(req, signals=("plant_input", "motor_angle"))
    finally:
        sim.stop()
    u = np.asarray(rec.signals["plant_input"], dtype=np.float64)   # exactly the drive's float output
    y = np.asarray(rec.signals["motor_angle"], dtype=np.float64)   # float32 of the FMU's theta1
    assert u.size == n and np.std(u) > 0.1
    assert truth["sim_fc_volt"] == pytest.approx(0.104, rel=1e-6) and np.isnan(truth["sim_fs_volt"])
    # FMPy: the same FMU from rest, u held over each step of 1/fs (ZOH at the communication points)
    dt = 1.0 / float(np.float32(FS))
    t = np.arange(n + 1) * dt
    sig = np.zeros(n + 1, dtype=[("time", np.float64), ("u", np.float64)])
    sig["time"], sig["u"][:n], sig["u"][n] = t, u, u[-1]
    res = simulate_fmu(LUGRE, fmi_type="CoSimulation", start_values=LUGRE_PARAMS, input=sig,
                       step_size=dt, output_interval=dt, stop_time=t[-1], output=["theta1"])
    ref = np.asarray(res["theta1"])[:n]      # theta1 at the start of step k: what drive_sim measured
    assert np.max(np.abs(ref)) > 0.05        # it moved (through stiction into sliding)
    err = np.max(np.abs(y - ref))
    assert err <= 2.0 ** -23 * np.max(np.abs(ref)), err   # float32 recording of the same doubles
    # and not by chance: a one-step shift of FMPy's samples is far off
    assert np.max(np.abs(y[1:] - ref[:-1])) > 100 * max(err, 1e-9)


# ---- an FMU built by FMPy's own tooling ----

TANH_MODEL = r"""
/* two-mass plant with tanh-smoothed Coulomb + viscous friction; fails on purpose from
 * t >= fail_at_s (a test of drive_sim's handling of a failing fmi2DoStep) */
#include <math.h>
#include <stdio.h>
#include "fmu_model.h"
#include "vars.h"
typedef struct { double x[4]; } m_t;
size_t model_size(void) { return sizeof(m_t); }
static void rhs(const double *r, const double *x, double u, double *dx)
{
    double f = r[VR_Fc] * tanh(x[1] / r[VR_v_eps]) + r[VR_b] * x[1];
    double s = r[VR_k] * (x[0] - x[2]) + r[VR_c] * (x[1] - x[3]);
    dx[0] = x[1]; dx[1] = (r[VR_km] * u - s - f) / r[VR_j1];
    dx[2] = x[3]; dx[3] = s / r[VR_j2];
}
static void outs(const m_t *m, double *r)
{ r[VR_theta1] = m->x[0]; r[VR_omega1] = m->x[1]; r[VR_theta2] = m->x[2]; }
int model_init(void *mv, double *r, char *msg, size_t n)
{
    m_t *m = mv;
    if (!(r[VR_v_eps] > 0.0)) { snprintf(msg, n, "v_eps must be > 0"); return -1; }
    for (int i = 0; i < 4; i++) m->x[i] = 0.0;
    outs(m, r);
    return 0;
}
int model_step(void *mv, double *r, double t, double h, char *msg, size_t n)
{
    m_t *m = mv;
    if (t + h > r[VR_fail_at_s]) { snprintf(msg, n, "solver failure (on purpose) at t = %g s", t); return -1; }
    const int sub = 10;
    double hs = h / sub, u = r[VR_u];
    for (int s = 0; s < sub; s++) {
        double k1[4], k2[4], k3[4], k4[4], y[4];
        rhs(r, m->x, u, k1); for (int i = 0; i < 4; i++) y[i] = m->x[i] + 0.5 * hs * k1[i];
        rhs(r, y, u, k2);    for (int i = 0; i < 4; i++) y[i] = m->x[i] + 0.5 * hs * k2[i];
        rhs(r, y, u, k3);    for (int i = 0; i < 4; i++) y[i] = m->x[i] + hs * k3[i];
        rhs(r, y, u, k4);
        for (int i = 0; i < 4; i++) m->x[i] += hs / 6.0 * (k1[i] + 2 * k2[i] + 2 * k3[i] + k4[i]);
    }
    outs(m, r);
    return 0;
}
"""

TANH_SPEC = {
    "model_identifier": "tanh_friction",
    "model_name": "two-mass plant, tanh Coulomb friction (test)",
    "variables": [
        {"name": "u", "causality": "input", "start": 0.0, "unit": "V"},
        {"name": "theta1", "causality": "output", "unit": "rad"},
        {"name": "omega1", "causality": "output", "unit": "rad/s"},
        {"name": "theta2", "causality": "output", "unit": "rad"},
        {"name": "j1", "causality": "parameter", "start": 1.0e-4},
        {"name": "j2", "causality": "parameter", "start": 2.0e-4},
        {"name": "k", "causality": "parameter", "start": 0.5},
        {"name": "c", "causality": "parameter", "start": 2.0e-4},
        {"name": "km", "causality": "parameter", "start": 0.05},
        {"name": "Fc", "causality": "parameter", "start": 6.5e-3},
        {"name": "v_eps", "causality": "parameter", "start": 0.01},
        {"name": "b", "causality": "parameter", "start": 1.5e-4},
        {"name": "fail_at_s", "causality": "parameter", "start": 1.0e9},
    ],
}


@pytest.fixture(scope="module")
def fmpy_built_fmu(tmp_path_factory):
    """A source FMU (modelDescription.xml with <SourceFiles>, sources/) compiled by
    fmpy.build.build_platform_binary (cmake) and zipped by fmpy.util.create_zip_archive."""
    pytest.importorskip("fmpy.build", reason="FMPy without its build helper")
    if shutil.which("cmake") is None and not os.path.exists(os.path.join(os.path.dirname(sys.executable), "cmake")):
        pytest.skip("cmake (FMPy's build helper needs it; pip install cmake) not found")
    sys.path.insert(0, os.path.join(REPO, "firmware_sim", "fmu"))
    import fmugen
    from fmpy.build import build_platform_binary
    from fmpy.util import create_zip_archive

    d = tmp_path_factory.mktemp("fmpy_build")
    src = d / "unzipped"
    (src / "sources").mkdir(parents=True)
    spec_text = yaml.safe_dump(TANH_SPEC, sort_keys=False)
    (d / "model.yaml").write_text(spec_text)
    spec, guid = fmugen.load_spec(str(d / "model.yaml"))
    xml = fmugen.model_description(spec, guid)
    files = ["model.c", "fmu_slave.c", "vars.c"]
    sources = "<SourceFiles>" + "".join(f'<File name="{f}"/>' for f in files) + "</SourceFiles>"
    xml = xml.replace('canNotUseMemoryManagementFunctions="false"/>',
                      f'canNotUseMemoryManagementFunctions="false">{sources}</CoSimulation>')
    (src / "modelDescription.xml").write_text(xml)
    h, c = fmugen.vars_sources(spec, guid)
    (src / "sources" / "vars.h").write_text(h)
    (src / "sources" / "vars.c").write_text(c)
    (src / "sources" / "model.c").write_text(TANH_MODEL)
    for f in ("fmu_slave.c", "fmu_model.h"):
        shutil.copy(os.path.join(REPO, "firmware_sim", "fmu", f), src / "sources" / f)
    (d / "cmake").mkdir()
    path = os.environ["PATH"]
    os.environ["PATH"] = os.path.dirname(sys.executable) + os.pathsep + path   # pip's cmake
    try:
        build_platform_binary(str(src), build_dir=str(d / "cmake"))
    finally:
        os.environ["PATH"] = path
    fmu = d / "tanh_friction.fmu"
    create_zip_archive(str(fmu), str(src))
    return str(fmu)


def _tanh_plant(tmp_path, fmu, **params):
    data = {"fmu": {"path": fmu, "input": "u", "output": "theta1", "parameters": params},
            "sensor": {"counts_per_rev": 2000, "noise_std": 0.0, "seed": 1},
            "truth": {"kfc_v": 6.5e-3 / 0.05}}
    path = tmp_path / "tanh_plant.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return str(path)


def _small_demo_config(tmp_path):
    with open(os.path.join(REPO, "configs", "demo.yaml"), encoding="utf-8") as fh:
        cfg = yaml.safe_load(fh)
    cfg["detect"].update(rms_levels=[1.0], realizations=2)
    cfg["quantify"].update(frequencies_hz=[2.5], rms_levels=[0.35], repeats=2, period_samples=1024)
    cfg["tune"].update(frequency_hz=1.25, period_samples=2048, settle_periods=1)
    cfg["tune"]["viscous"]["enabled"] = False
    cfg["tune"]["sweep"]["points"] = 3
    path = tmp_path / "small.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return str(path)


def test_an_fmu_built_by_fmpys_tooling_runs_through_fftune_demo(fmpy_built_fmu, tmp_path, capsys):
    with zipfile.ZipFile(fmpy_built_fmu) as z:
        assert "binaries/linux64/tanh_friction.so" in z.namelist()   # cmake's build, not ours
    plant = _tanh_plant(tmp_path, fmpy_built_fmu, Fc=6.5e-3, b=1.5e-4)
    out = tmp_path / "out"
    code = main(["demo", "--config", _small_demo_config(tmp_path), "--plant", plant, "--out", str(out),
                 "--no-progress"])
    printed = capsys.readouterr().out
    assert code == 0, printed
    assert "overrides of the built-in plant do not apply" in printed   # demo.yaml's sim.overrides
    res = yaml.safe_load(open(out / "results.yaml"))
    s = res["tune"]["search"]
    assert res["tune"]["true_coulomb_v"] == pytest.approx(0.13, rel=1e-6)
    if s["converged"]:
        # K_fc* against the tanh law's sliding level Fc / km = 0.13 V
        assert abs(s["k_fc_star"] - 0.13) <= 3 * s["sigma_v"] + 0.05 * 0.13, s
    else:
        assert s["stop_reason"], s


# ---- bad FMUs: one line each, nothing moves ----

def _demo_error(tmp_path, capsys, plant):
    out = tmp_path / "out"
    code = main(["demo", "--plant", plant, "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert len(err) == 1 and err[0].startswith("fftune: error: "), err
    assert not out.exists()        # failed before the first experiment: nothing left
    return err[0]


def _variant(tmp_path, edit, name="bad.fmu"):
    """lugre.fmu rewritten: edit(members dict name -> bytes) changes it."""
    with zipfile.ZipFile(LUGRE) as z:
        members = {n: z.read(n) for n in z.namelist()}
    edit(members)
    path = tmp_path / name
    with zipfile.ZipFile(path, "w") as z:
        for n, data in members.items():
            z.writestr(n, data)
    return str(path)


SO = "binaries/linux64/fftune_lugre.so"


def test_a_missing_fmu_file_is_one_line(tmp_path, capsys):
    plant = plant_file(tmp_path, fmu="models/nowhere.fmu")
    line = _demo_error(tmp_path, capsys, plant)
    assert plant in line and "key 'fmu.path'" in line and "models/nowhere.fmu" in line


def test_a_missing_variable_is_one_line_naming_it(tmp_path, capsys):
    plant = plant_file(tmp_path, input="voltage")
    line = _demo_error(tmp_path, capsys, plant)
    assert plant in line and "key 'fmu.input'" in line and "'voltage'" in line and "input variables: u" in line
    plant = plant_file(tmp_path, parameters={"Fc": 5e-3, "sigma_0": 20.0})
    line = _demo_error(tmp_path, capsys, plant)
    assert "key 'fmu.parameters.sigma_0'" in line and "'sigma_0'" in line


@pytest.mark.parametrize("key,name,has,needs", [
    ("output", "Fc", "parameter", "output"),
    ("input", "theta1", "output", "input"),
])
def test_a_wrong_causality_is_one_line_naming_the_variable(tmp_path, capsys, key, name, has, needs):
    plant = plant_file(tmp_path, **{key: name})
    line = _demo_error(tmp_path, capsys, plant)
    assert f"key 'fmu.{key}'" in line and f"'{name}'" in line and f"causality '{has}'" in line
    assert f"needed: {needs}" in line


def test_a_binary_for_another_platform_is_one_line(tmp_path, capsys):
    def aarch64(m):
        so = bytearray(m[SO])
        so[18:20] = (183).to_bytes(2, "little")      # e_machine: AArch64
        m[SO] = bytes(so)
    line = _demo_error(tmp_path, capsys, plant_file(tmp_path, fmu=_variant(tmp_path, aarch64)))
    assert SO in line and "aarch64" in line and "another platform" in line

    def windows_only(m):
        m["binaries/win64/fftune_lugre.dll"] = m.pop(SO)
    line = _demo_error(tmp_path, capsys, plant_file(tmp_path, fmu=_variant(tmp_path, windows_only, "win.fmu")))
    assert "no binary for this platform (linux64" in line and "win64" in line


def test_an_unsupported_version_or_kind_is_one_line(tmp_path, capsys):
    def fmi1(m):
        m["modelDescription.xml"] = m["modelDescription.xml"].replace(b'fmiVersion="2.0"', b'fmiVersion="1.0"')
    line = _demo_error(tmp_path, capsys, plant_file(tmp_path, fmu=_variant(tmp_path, fmi1)))
    assert "bad.fmu" in line and ("FMI 1.0" in line or "modelDescription.xml" in line)

    def me_only(m):
        xml = m["modelDescription.xml"].decode()
        xml = xml.replace("<CoSimulation ", "<ModelExchange ")
        m["modelDescription.xml"] = xml.encode()
    line = _demo_error(tmp_path, capsys, plant_file(tmp_path, fmu=_variant(tmp_path, me_only, "me.fmu")))
    assert "model exchange only" in line

    notzip = tmp_path / "notzip.fmu"
    notzip.write_bytes(b"PK but not really a zip")
    line = _demo_error(tmp_path, capsys, plant_file(tmp_path, fmu=str(notzip)))
    assert "not an FMU (not a zip archive)" in line


def test_an_unloadable_binary_is_drive_sims_one_line(tmp_path, capsys):
    """The host's checks pass (an x86-64 ELF header), drive_sim's dlopen does not."""
    def truncated(m):
        m[SO] = m[SO][:64]
    plant = plant_file(tmp_path, fmu=_variant(tmp_path, truncated))
    line = _demo_error(tmp_path, capsys, plant)
    assert line.startswith("fftune: error: drive_sim: ") and plant in line
    assert "cannot load binaries/linux64/fftune_lugre.so" in line


@pytest.mark.parametrize("parameters,words", [
    ({"Fc": 9e-3, "Fs": 5e-3}, "Fs = 0.005: must be >= Fc = 0.009"),
    ({"j1": -2e-5}, "parameter j1 = -2e-05: must be finite and > 0"),          # strictly positive
    ({"sigma0": 0.0}, "parameter sigma0 = 0: must be finite and > 0"),
    ({"sigma1": -0.5}, "parameter sigma1 = -0.5: must be finite and >= 0"),    # non-negative
    ({"substeps": 2.5}, "parameter substeps = 2.5: a whole number 1 .. 10000"),
    ({"substeps": 10001}, "parameter substeps = 10001: a whole number 1 .. 10000"),
])
def test_a_parameter_the_fmu_refuses_at_initialisation_is_one_line(tmp_path, capsys, parameters, words):
    plant = plant_file(tmp_path, parameters=parameters)
    line = _demo_error(tmp_path, capsys, plant)
    assert "fmi2ExitInitializationMode returned fmi2Error" in line and words in line


def test_a_step_that_fails_is_one_line_before_the_drive_exists(fmpy_built_fmu, tmp_path, capsys):
    plant = _tanh_plant(tmp_path, fmpy_built_fmu, fail_at_s=0.0)
    line = _demo_error(tmp_path, capsys, plant)
    assert line.startswith("fftune: error: drive_sim: ") and plant in line
    assert "fmi2DoStep(t = 0 s" in line and "returned fmi2Error" in line and "on purpose" in line


def test_a_step_that_fails_mid_run_disables_the_drive(fmpy_built_fmu, tmp_path, capsys):
    """The trial step passes; the FMU fails at t = 0.5 s in the demo's first run: the drive is
    disabled at once, the run stops, and the one error line carries drive_sim's reason."""
    plant = _tanh_plant(tmp_path, fmpy_built_fmu, fail_at_s=0.5)
    out = tmp_path / "out"
    code = main(["demo", "--config", _small_demo_config(tmp_path), "--plant", plant, "--out", str(out),
                 "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    line = err[0]
    assert line.startswith("fftune: error: run stopped by the drive") and "; drive_sim: " in line
    assert plant in line and "fmi2DoStep(t = 0.5" in line and "on purpose" in line
    assert "the drive is disabled" in line


# ---- plant file keys, machine axes, overrides ----

def test_plant_file_keys_are_checked(tmp_path):
    from fftune.host.fmu import drive_sim_text

    with pytest.raises(FftuneError, match=r"key 'fmu.inptu': unknown key"):
        drive_sim_text(plant_file(tmp_path, inptu="u"))
    p = plant_file(tmp_path)
    data = yaml.safe_load(open(p))
    data["plant"] = {"coulomb": 1e-3}
    open(p, "w").write(yaml.safe_dump(data))
    with pytest.raises(FftuneError, match=r"key 'plant': unknown section next to 'fmu' \(the built-in"):
        drive_sim_text(p)
    with pytest.raises(FftuneError, match=r"key 'fmu.parameters.Fc': expected a number"):
        drive_sim_text(plant_file(tmp_path, parameters={"Fc": "small"}))
    text, _ = drive_sim_text(plant_file(tmp_path, load_output="theta2"))
    assert 'load_output: "theta2"' in text and "load_output_vr: 3" in text
    assert 'p0_name: "Fc"' in text and "p0_vr: 11" in text and "p0_value: 0.0052" in text


def test_overrides_of_the_built_in_plant_refuse_an_fmu_plant(tmp_path):
    from fftune.host.sim import derived_plant_text

    with pytest.raises(FftuneError, match=r"axis 'x' plant_overrides: the plant .* is an FMU"):
        derived_plant_text(plant_file(tmp_path), {"plant": {"coulomb": 1e-3}}, where="m.yaml: axis 'x' plant_overrides")


def test_a_machine_axis_takes_an_fmu_plant(tmp_path):
    from fftune.host.drive import BusOptions, DriveClient
    from fftune.host.sim import start_drive_sim

    fmu_plant = plant_file(tmp_path)
    builtin = os.path.join(REPO, "configs", "plant_twomass.yaml")
    sim = start_drive_sim(builtin, node_id=1, extra=["--axis", f"1:{builtin}", "--axis", f"2:{fmu_plant}"],
                          log_path=str(tmp_path / "drive_sim.log"))
    try:
        truths = {}
        for nid in (1, 2):
            with DriveClient(BusOptions(port=sim.port, host=sim.host, eds=EDS, node_id=nid), progress=False,
                             heartbeat_ms=0) as d:
                truths[nid] = d.plant_truth()
    finally:
        sim.stop()
    assert truths[1]["sim_fc_volt"] == pytest.approx(5.785e-3 / 0.05, rel=1e-6)   # the built-in plant
    assert truths[2]["sim_fc_volt"] == pytest.approx(0.104, rel=1e-6)            # the FMU's truth:


def test_builds_with_the_built_in_plant_only_refuse_an_fmu_plant_file(tmp_path):
    """libfwsim (the C tests' and benches' simulation, no FMU loader) names the reason;
    a truth: section without fmu: is refused (the built-in plant's truth is its parameters)."""
    sys.path.insert(0, os.path.join(REPO, "firmware_sim", "tests"))
    from fwsim import FwSim

    from fftune.host.fmu import drive_sim_plant

    view = drive_sim_plant(plant_file(tmp_path))
    with pytest.raises(ValueError, match=r"names an FMU plant \(section fmu\): drive_sim co-simulates it"):
        FwSim(view)
    builtin = tmp_path / "builtin_truth.yaml"
    builtin.write_text("plant:\n  coulomb: 5.0e-3\n  static: 6.0e-3\ntruth:\n  kfc_v: 0.1\n")
    with pytest.raises(ValueError, match=r"builtin_truth.yaml:4: section 'truth' is for an FMU plant"):
        FwSim(str(builtin))


# ---- FMI 3.0: an FMU made from FMPy's own template (fmpy.template.create_fmu) ----

FMI3_STEP = r"""
    Model *m = (Model *)instance;
    const int sub = 10;
    double hs = communicationStepSize / sub;
    for (int s = 0; s < sub; s++) {
        double x[4] = {m->theta1, m->omega1, m->theta2, m->omega2}, k[4][4], y[4];
        for (int st = 0; st < 4; st++) {
            const double *z = st == 0 ? x : y;
            double g = m->Fc + (m->Fs - m->Fc) * exp(-(z[1] / m->vs) * (z[1] / m->vs));
            double f = g * tanh(z[1] / m->v_eps) + m->b * z[1];
            double spring = m->k * (z[0] - z[2]) + m->c * (z[1] - z[3]);
            k[st][0] = z[1];
            k[st][1] = (m->km * m->u - spring - f) / m->j1;
            k[st][2] = z[3];
            k[st][3] = spring / m->j2;
            double a = st == 2 ? hs : 0.5 * hs;
            for (int i = 0; i < 4; i++) y[i] = x[i] + a * k[st][i];
        }
        m->theta1 += hs / 6 * (k[0][0] + 2 * k[1][0] + 2 * k[2][0] + k[3][0]);
        m->omega1 += hs / 6 * (k[0][1] + 2 * k[1][1] + 2 * k[2][1] + k[3][1]);
        m->theta2 += hs / 6 * (k[0][2] + 2 * k[1][2] + 2 * k[2][2] + k[3][2]);
        m->omega2 += hs / 6 * (k[0][3] + 2 * k[1][3] + 2 * k[2][3] + k[3][3]);
    }
    m->time = currentCommunicationPoint + communicationStepSize;
    *eventHandlingNeeded = fmi3False;
    *terminateSimulation = fmi3False;
    *earlyReturn = fmi3False;
    *lastSuccessfulTime = m->time;
    UNUSED(noSetFMUStatePriorToCurrentPoint);
    return fmi3OK;
}
"""
FMI3_PARAMS = {"j1": 1.0e-4, "j2": 2.0e-4, "k": 0.5, "c": 2.0e-4, "km": 0.05, "Fc": 6.0e-3, "Fs": 9.0e-3,
               "vs": 0.2, "v_eps": 0.01, "b": 1.2e-4}


@pytest.fixture(scope="module")
def fmi3_fmu(tmp_path_factory):
    """An FMI 3.0 co-simulation FMU from FMPy's template (create_fmu), its fmi3DoStep filled
    in with a two-mass plant (Stribeck + tanh Coulomb + viscous friction), built by
    fmpy.build.build_platform_binary."""
    from fmpy.build import build_platform_binary
    from fmpy.model_description import CoSimulation, ModelDescription, ModelVariable, Unknown
    from fmpy.template import create_fmu
    from fmpy.util import create_zip_archive

    md = ModelDescription()
    md.fmiVersion, md.modelName, md.instantiationToken = "3.0", "stribeck3", "{3f0c8c1e-0000-4000-8000-fftune000003}"
    md.description, md.generationTool = "two-mass plant, Stribeck + tanh friction (test)", "fftune tests"
    md.generationDateAndTime = "2026-01-01T00:00:00Z"
    md.coSimulation = CoSimulation(modelIdentifier="stribeck3")
    names = [("time", "independent", "continuous", None), ("u", "input", "continuous", "0")]
    names += [(n, "output" if n == "theta1" else "local", "continuous", None)
              for n in ("theta1", "omega1", "theta2", "omega2")]
    names += [(n, "parameter", "fixed", repr(v)) for n, v in FMI3_PARAMS.items()]
    for vr, (name, causality, variability, start) in enumerate(names):
        v = ModelVariable(name=name, valueReference=vr, type="Float64", causality=causality,
                          variability=variability, start=start, description=name)
        if causality == "local":
            v.initial = None
        md.modelVariables.append(v)
        if causality == "output":
            md.outputs.append(Unknown(variable=v))
            md.initialUnknowns.append(Unknown(variable=v))
    d = tmp_path_factory.mktemp("fmi3")
    src_fmu = d / "template.fmu"
    create_fmu(md, str(src_fmu))
    unz = d / "unzipped"
    with zipfile.ZipFile(src_fmu) as z:
        z.extractall(unz)
    c = (unz / "sources" / "model.c").read_text()
    i = c.index("fmi3Status fmi3DoStep(")
    body = c.index("{", i)
    end = c.index("return fmi3OK;\n}", body) + len("return fmi3OK;\n}")
    c = c[:body + 1] + FMI3_STEP + c[end:]
    c = c.replace("#include <string.h>", "#include <string.h>\n#include <stdlib.h>\n#include <math.h>", 1)
    (unz / "sources" / "model.c").write_text(c)
    (d / "cmake").mkdir()
    path = os.environ["PATH"]
    os.environ["PATH"] = os.path.dirname(sys.executable) + os.pathsep + path   # pip's cmake
    try:
        build_platform_binary(str(unz), build_dir=str(d / "cmake"))
    finally:
        os.environ["PATH"] = path
    fmu = d / "stribeck3.fmu"
    create_zip_archive(str(fmu), str(unz))
    return str(fmu)


def test_an_fmi3_fmu_from_fmpys_template_runs_as_fmpy_runs_it(fmi3_fmu, tmp_path):
    from fmpy import simulate_fmu

    from fftune.host.drive import BusOptions, DriveClient
    from fftune.host.fmu import drive_sim_text
    from fftune.host.sim import start_drive_sim

    data = {"fmu": {"path": fmi3_fmu, "input": "u", "output": "theta1", "parameters": {"Fc": 6.5e-3}},
            "sensor": {"counts_per_rev": 0}, "truth": {"kfc_v": 0.13}, "controller": {"kp": 0.0, "kd": 0.0}}
    plant = tmp_path / "fmi3.yaml"
    plant.write_text(yaml.safe_dump(data))
    text, _ = drive_sim_text(str(plant))
    assert "fmi_version: 3" in text and 'guid: "{3f0c8c1e-0000-4000-8000-fftune000003}"' in text
    n = 1024
    req = {"exc_kind": 3, "exc_inject": 1, "exc_amplitude": 0.45, "exc_offset": -0.05, "exc_period": n,
           "ms_k_min": 1, "ms_k_max": 150, "ms_group": 0, "ms_seed": 4, "ms_realization": 0,
           "exc_settle_periods": 0, "exc_record_periods": 1}
    sim = start_drive_sim(str(plant), log_path=str(tmp_path / "drive_sim.log"))
    try:
        with DriveClient(BusOptions(port=sim.port, host=sim.host, eds=EDS), progress=False) as d:
            assert d.plant_truth()["sim_fc_volt"] == pytest.approx(0.13, rel=1e-6)
            d.enable()
            rec = d.run(req, signals=("plant_input", "motor_angle"))
    finally:
        sim.stop()
    u = np.asarray(rec.signals["plant_input"], dtype=np.float64)
    y = np.asarray(rec.signals["motor_angle"], dtype=np.float64)
    dt = 1.0 / float(np.float32(FS))
    t = np.arange(n + 1) * dt
    sig = np.zeros(n + 1, dtype=[("time", np.float64), ("u", np.float64)])
    sig["time"], sig["u"][:n], sig["u"][n] = t, u, u[-1]
    res = simulate_fmu(fmi3_fmu, fmi_type="CoSimulation", start_values={"Fc": 6.5e-3}, input=sig,
                       step_size=dt, output_interval=dt, stop_time=t[-1], output=["theta1"])
    ref = np.asarray(res["theta1"])[:n]
    assert np.max(np.abs(ref)) > 0.05
    assert np.max(np.abs(y - ref)) <= 2.0 ** -23 * np.max(np.abs(ref))


def test_an_nmt_reset_node_starts_the_fmu_again(tmp_path):
    """After a run the open-loop plant is displaced; NMT reset node re-instantiates the FMU,
    so the same run again gives the first run's samples (without it, it would start from the
    displaced state)."""
    import time

    from fftune.host.drive import BusOptions, DriveClient
    from fftune.host.sim import start_drive_sim

    plant = plant_file(tmp_path)
    req = {"exc_kind": 1, "exc_inject": 1, "exc_amplitude": 0.3, "exc_offset": 0.05, "exc_period": 1024,
           "exc_sine_cycles": 2, "exc_settle_periods": 0, "exc_record_periods": 1}
    sim = start_drive_sim(plant, log_path=str(tmp_path / "drive_sim.log"))
    try:
        with DriveClient(BusOptions(port=sim.port, host=sim.host, eds=EDS), progress=False, heartbeat_ms=250) as d:
            d.enable()
            first = np.asarray(d.run(req, signals=("motor_angle",)).signals["motor_angle"])
            again = np.asarray(d.run(req, signals=("motor_angle",)).signals["motor_angle"])
            d.node.nmt.state = "RESET"
            time.sleep(0.3)
            d.write(0x1016, 1, (127 << 16) | 1000)   # the reset cleared the consumer: re-arm it
            d.enable()
            reset = np.asarray(d.run(req, signals=("motor_angle",)).signals["motor_angle"])
    finally:
        sim.stop()
    assert np.max(np.abs(first)) > 0.05 and abs(first[-1]) > 0.01      # it moved and stayed displaced
    assert np.max(np.abs(again - first)) > 1e-3                           # no reset: another start
    np.testing.assert_array_equal(reset, first)


def test_drive_sim_reading_an_fmu_section_names_what_is_wrong(tmp_path):
    """drive_sim reads the view fftune writes; a user's plant file given to it directly, a
    view with a key missing or a value of the wrong kind is one line naming file and key."""
    import subprocess

    from fftune.host.fmu import drive_sim_plant
    from fftune.host.resources import drive_sim_path

    def drive_sim_error(path):
        r = subprocess.run([drive_sim_path(), "--config", str(path), "--port", "0"], capture_output=True,
                           text=True, timeout=20)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("drive_sim: error: "), r.stderr
        return lines[0]

    user = plant_file(tmp_path)
    line = drive_sim_error(user)
    assert user in line and "goes to fftune sim|demo --plant FILE" in line
    view = open(drive_sim_plant(user)).read()
    no_guid = tmp_path / "no_guid.yaml"
    no_guid.write_text("\n".join(ln for ln in view.splitlines() if not ln.startswith("  guid:")) + "\n")
    assert "fmu.guid missing" in drive_sim_error(no_guid)
    bad_vr = tmp_path / "bad_vr.yaml"
    bad_vr.write_text(view.replace("  output_vr: 1\n", "  output_vr: -1\n"))
    line = drive_sim_error(bad_vr)
    assert "bad_vr.yaml:" in line and "'-1' is not an unsigned 32-bit integer" in line
    wrong_guid = tmp_path / "wrong_guid.yaml"
    wrong_guid.write_text(view.replace('  guid: "{', '  guid: "{0'))
    line = drive_sim_error(wrong_guid)
    assert "fmi2Instantiate (co-simulation, GUID {0" in line and "returned NULL" in line
    assert "does not match the FMU's" in line           # the FMU's own log message
