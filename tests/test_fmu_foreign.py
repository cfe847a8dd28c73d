"""FMUs written by someone else run through `fftune demo --plant` (docs/fmu.md, "FMUs from
other exporters").

The FMUs of tests/data/fmu_foreign/ are not made with fftune's fmugen.py / fmu_slave.c: a
hand-written FMI 2.0 co-simulation slave and hand-written modelDescription.xml files, compiled
by FMPy's CMake project (fmpy.build.build_platform_binary), with friction laws fftune does not
ship (smooth Stribeck + viscous; Maxwell-slip with a current loop and a one-step delay;
Karnopp stick-slip with backlash; elasto-plastic) and the habits of other exporters: structured names with
dots, brackets and der(), declared units and types, Integer / Boolean parameters, fixed /
tunable variability, calculated parameters, canHandleVariableCommunicationStepSize false, a
GUID check, a model identifier other than the file name, binaries for win64 too, resources
read through the resource URI, a logger called every step, fmi2Warning from steps, embedded
code that can be instantiated only once per process. The plant
files and the cache live under paths with spaces and non-ASCII letters.

Each bad one is one `fftune: error:` line naming the plant file and the variable or function,
exit status 2, nothing written. The full demo per law (the defaults, K_fc* against the
truth): tests/bench/bench_fmu_foreign.py.
"""
import os
import re
import shutil
import sys

import pytest
import yaml

from fftune.host.cli import main
from host_fixtures import REPO, drive_sim_missing_reason

sys.path.insert(0, os.path.join(REPO, "tests", "data", "fmu_foreign"))
import foreign_fmus as foreign  # noqa: E402  (tests/data/fmu_foreign/foreign_fmus.py)

pytestmark = [
    pytest.mark.skipif(drive_sim_missing_reason() is not None, reason=drive_sim_missing_reason() or ""),
    pytest.mark.skipif(shutil.which("cmake") is None
                       and not os.path.exists(os.path.join(os.path.dirname(sys.executable), "cmake")),
                       reason="cmake not found (FMPy's build_platform_binary needs it; pip install cmake)"),
]

ODD_DIR = "plants of someone else ü"


@pytest.fixture(autouse=True)
def _fmu_cache(tmp_path_factory, monkeypatch):
    """FMUs unpack into a per-session cache whose path has a space and a non-ASCII letter
    (the resource URI the FMU decodes)."""
    monkeypatch.setenv("FFTUNE_FMU_CACHE", str(tmp_path_factory.getbasetemp() / "fmu cache é"))


@pytest.fixture(scope="module")
def fmus():
    """name -> path of the built FMU (built once per source content, cached)."""
    return {name: foreign.build(name) for name in foreign.FOREIGN}


def plant_file(tmp_path, fmu, name, *, copy=True, file_name="plant.yaml", **over):
    """The plant file of FOREIGN[name] (keys as an outside engineer writes them), the FMU
    copied beside it under its own file name; ``over`` replaces fmu: keys (None drops one)."""
    spec = foreign.FOREIGN[name]
    folder = tmp_path / ODD_DIR
    folder.mkdir(exist_ok=True)
    path = fmu
    if copy:
        shutil.copy(fmu, folder / os.path.basename(fmu))
        path = os.path.basename(fmu)          # relative: beside the plant file
    f = {"path": path, "input": spec["input"], "output": spec["output"],
         "load_output": spec["load_output"], "parameters": dict(spec["parameters"])}
    f.update(over)
    data = {"fmu": {k: v for k, v in f.items() if v is not None},
            "sensor": {"counts_per_rev": 2000, "noise_std": 0.0, "seed": 1},
            "truth": dict(spec["truth"])}
    out = folder / file_name
    out.write_text(yaml.safe_dump(data, sort_keys=False, allow_unicode=True), encoding="utf-8")
    return str(out)


def small_demo_config(tmp_path):
    """configs/demo.yaml with fewer, shorter experiments (the full demo: the bench)."""
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


# ---- good FMUs: through fftune demo --plant, fftune unchanged ----

@pytest.mark.parametrize("name", ["stribeck_stage", "maxwell_slip", "backlash_karnopp"])   # (elastoplastic: the bench)
def test_a_foreign_fmu_runs_through_fftune_demo(fmus, tmp_path, capsys, name):
    """BacklashStage with the shortest plant file (fmu: path, input, output; no sensor, no
    truth: K_fc* is compared with the law's level here, not in the report)."""
    plant = plant_file(tmp_path, fmus[name], name)
    minimal = name == "backlash_karnopp"
    if minimal:
        spec = foreign.FOREIGN[name]
        with open(plant, "w", encoding="utf-8") as fh:
            fh.write(f"fmu:\n  path: {os.path.basename(fmus[name])}\n  input: {spec['input']}\n"
                     f"  output: {spec['output']}\n")
    out = tmp_path / "out"
    code = main(["demo", "--config", small_demo_config(tmp_path), "--plant", plant, "--out", str(out),
                 "--no-progress"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert captured.err.strip() == "", captured.err          # (the FMU's chatter stays in drive_sim)
    res = yaml.safe_load(open(out / "results.yaml", encoding="utf-8"))
    truth = foreign.FOREIGN[name]["truth"]["kfc_v"]
    if minimal:
        assert res["tune"]["true_coulomb_v"] is None
    else:
        assert res["tune"]["true_coulomb_v"] == pytest.approx(truth, rel=1e-6)   # (float32 in the drive)
    s = res["tune"]["search"]
    if s["converged"]:
        assert abs(s["k_fc_star"] - truth) <= 3 * s["sigma_v"] + 0.05 * truth, s
    else:
        assert s["stop_reason"], s


# ---- FMPy (the reference) and drive_sim run a foreign FMU to the same samples ----

def test_fmpy_and_drive_sim_agree_on_a_foreign_fmu_whose_solver_follows_the_tolerance(fmus, tmp_path):
    """maxwell_slip sizes its sub-steps from the tolerance of fmi2SetupExperiment (the
    DefaultExperiment's 1e-8: 20 sub-steps a controller step; none given: its own 1e-4, one
    sub-step). FMPy passes the DefaultExperiment tolerance; drive_sim must too, else the
    samples differ by far more than the float32 recording."""
    import numpy as np
    from fmpy import simulate_fmu

    from fftune.host.drive import BusOptions, DriveClient
    from fftune.host.sim import start_drive_sim
    from host_fixtures import EDS

    fmu = fmus["maxwell_slip"]
    # (delay false: with the one-step delay the first step would apply the input of the
    # initialisation, which FMPy sets from the signal and drive_sim to 0 -- the drive's output then)
    params = dict(foreign.FOREIGN["maxwell_slip"]["parameters"], tau_i=3.0e-4, delay=False)
    plant = plant_file(tmp_path, fmu, "maxwell_slip", parameters=params)
    data = yaml.safe_load(open(plant, encoding="utf-8"))
    data["controller"] = {"kp": 0.0, "kd": 0.0}             # open loop: the multisine is the plant input
    data["sensor"]["counts_per_rev"] = 0
    open(plant, "w", encoding="utf-8").write(yaml.safe_dump(data, allow_unicode=True))
    n = 2048
    req = {"exc_kind": 3, "exc_inject": 1, "exc_amplitude": 0.4, "exc_offset": -0.05, "exc_period": n,
           "ms_k_min": 1, "ms_k_max": 150, "ms_group": 0, "ms_seed": 7, "ms_realization": 0,
           "exc_settle_periods": 0, "exc_record_periods": 1}
    sim = start_drive_sim(plant, log_path=str(tmp_path / "drive_sim.log"))
    try:
        with DriveClient(BusOptions(port=sim.port, host=sim.host, eds=EDS), progress=False) as d:
            d.enable()
            rec = d.run(req, signals=("plant_input", "motor_angle"))
    finally:
        sim.stop()
    u = np.asarray(rec.signals["plant_input"], dtype=np.float64)
    y = np.asarray(rec.signals["motor_angle"], dtype=np.float64)
    assert u.size == n and np.std(u) > 0.1
    dt = 1.0 / float(np.float32(2560.0))
    t = np.arange(n + 1) * dt
    sig = np.zeros(n + 1, dtype=[("time", np.float64), ("u_cmd", np.float64)])
    sig["time"], sig["u_cmd"][:n], sig["u_cmd"][n] = t, u, u[-1]
    ref = {}
    for tol in (None, 1e-4):                   # None: FMPy takes the DefaultExperiment's 1e-8
        res = simulate_fmu(fmu, fmi_type="CoSimulation", start_values=params, input=sig, step_size=dt,
                           output_interval=dt, stop_time=t[-1], output=["phi[1]"], relative_tolerance=tol)
        ref[tol] = np.asarray(res["phi[1]"])[:n]
    assert np.max(np.abs(ref[None])) > 0.05                  # it slid
    bound = 2.0 ** -23 * np.max(np.abs(ref[None]))           # the float32 recording of the same doubles
    assert np.max(np.abs(y - ref[None])) <= bound
    assert np.max(np.abs(ref[1e-4] - ref[None])) > 100 * bound   # (the tolerance matters for this FMU)


# ---- bad FMUs and plant files: one line each, nothing moves ----

def demo_error(tmp_path, capsys, plant):
    out = tmp_path / "out"
    code = main(["demo", "--plant", plant, "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert len(err) == 1 and err[0].startswith("fftune: error: "), err
    assert not out.exists()        # failed before the drive was enabled: nothing written
    return err[0]


def test_a_wrong_guid_is_drive_sims_one_line_with_the_fmus_reason(fmus, tmp_path, capsys):
    def guid(m):
        m["modelDescription.xml"] = m["modelDescription.xml"].replace(b"msm-plant-2.1.0-7f3e", b"msm-plant-2.0.9-0000")
    fmu = foreign.rezip(fmus["maxwell_slip"], tmp_path / "old guid.fmu", guid)
    plant = plant_file(tmp_path, fmu, "maxwell_slip")
    line = demo_error(tmp_path, capsys, plant)
    assert line.startswith("fftune: error: drive_sim: ") and plant in line
    assert "fmi2Instantiate (co-simulation, GUID msm-plant-2.0.9-0000) returned NULL" in line
    assert "wrong GUID msm-plant-2.0.9-0000, expected msm-plant-2.1.0-7f3e" in line   # the FMU's own log


def test_a_source_only_fmu_is_refused_in_one_line_naming_why(fmus, tmp_path, capsys):
    def strip(m):
        for n in [n for n in m if n.startswith("binaries/")]:
            del m[n]
    fmu = foreign.rezip(fmus["backlash_karnopp"], tmp_path / "source only.fmu", strip)
    line = demo_error(tmp_path, capsys, plant_file(tmp_path, fmu, "backlash_karnopp"))
    assert "source only.fmu" in line and "binaries/linux64/bls_cs.so" in line
    assert "no binary for this platform" in line and "a source FMU" in line


def test_a_windows_only_fmu_is_one_line_listing_what_it_has(fmus, tmp_path, capsys):
    def windows_only(m):
        del m["binaries/linux64/StribeckStage.so"]
    fmu = foreign.rezip(fmus["stribeck_stage"], tmp_path / "win.fmu", windows_only)
    line = demo_error(tmp_path, capsys, plant_file(tmp_path, fmu, "stribeck_stage"))
    assert "binaries/linux64/StribeckStage.so" in line and "the FMU has win64" in line


@pytest.mark.parametrize("mode,status", [(1, "fmi2Discard"), (2, "fmi2Pending"), (3, "fmi2Fatal")])
def test_a_step_returning_discard_pending_or_fatal_is_one_line(fmus, tmp_path, capsys, mode, status):
    params = dict(foreign.FOREIGN["maxwell_slip"]["parameters"], failMode=mode, failTime=0.0)
    plant = plant_file(tmp_path, fmus["maxwell_slip"], "maxwell_slip", parameters=params)
    line = demo_error(tmp_path, capsys, plant)
    assert line.startswith("fftune: error: drive_sim: ") and plant in line
    assert f"fmi2DoStep(t = 0 s, h = 0.000390625 s) with input 'u_cmd' = 0 returned {status}" in line
    assert f"failMode {mode} at t = 0 s (on purpose)" in line


def test_a_missing_resource_is_one_line_from_the_fmu(fmus, tmp_path, capsys):
    def no_resources(m):
        del m["resources/elements.csv"]
    fmu = foreign.rezip(fmus["maxwell_slip"], tmp_path / "no resources.fmu", no_resources)
    line = demo_error(tmp_path, capsys, plant_file(tmp_path, fmu, "maxwell_slip"))
    assert "fmi2ExitInitializationMode returned fmi2Error" in line
    assert "resources/elements.csv (the resource location given to fmi2Instantiate)" in line


@pytest.mark.parametrize("key,value,words", [
    ("output", "w[1]", ["key 'fmu.output'", "'w[1]'", "causality 'local'", "needed: output"]),
    ("output", "phi[3]", ["key 'fmu.output'", "no variable 'phi[3]'", "output variables: phi[1], phi[2]"]),
    ("input", "tau_i", ["key 'fmu.input'", "'tau_i'", "causality 'parameter'", "needed: input"]),
    ("parameters", {"Ftot": 6e-3}, ["key 'fmu.parameters.Ftot'", "causality 'calculatedParameter'"]),
    ("parameters", {"nElem": 2.5}, ["key 'fmu.parameters.nElem'", "Integer: expected a whole number"]),
    ("parameters", {"delay": 1}, ["key 'fmu.parameters.delay'", "Boolean: expected true or false"]),
])
def test_a_wrong_variable_is_one_line_naming_it(fmus, tmp_path, capsys, key, value, words):
    plant = plant_file(tmp_path, fmus["maxwell_slip"], "maxwell_slip", **{key: value})
    line = demo_error(tmp_path, capsys, plant)
    assert plant in line
    for w in words:
        assert w in line, line


@pytest.mark.parametrize("params,words", [
    ({"hMax": 2.0e-3}, ["key 'fmu.parameters.hMax'", "0.002 is outside the range", "(min 1e-07, max 0.001)"]),
    ({"gap": -1.0e-3}, ["key 'fmu.parameters.gap'", "(min 0.0, max inf)"]),
    ({"Fc": float("inf")}, ["key 'fmu.parameters.Fc'", "expected a finite number, got inf"]),
])
def test_a_start_value_outside_what_the_fmu_declares_is_one_line(fmus, tmp_path, capsys, params, words):
    """min / max of the variable (hMax) or of its declared type; before drive_sim starts."""
    plant = plant_file(tmp_path, fmus["backlash_karnopp"], "backlash_karnopp", parameters=params)
    line = demo_error(tmp_path, capsys, plant)
    assert plant in line
    for w in words:
        assert w in line, line


@pytest.mark.parametrize("key,name,unit", [("output", "body.w", "rad/s"), ("load_output", "der(body.phi)", None)])
def test_an_output_that_is_no_angle_in_rad_is_one_line(fmus, tmp_path, capsys, key, name, unit):
    """body.w's unit comes from its declared type (Modelica.SIunits.AngularVelocity)."""
    plant = plant_file(tmp_path, fmus["stribeck_stage"], "stribeck_stage", **{key: name})
    line = demo_error(tmp_path, capsys, plant)
    assert f"key 'fmu.{key}'" in line and f"'{name}'" in line
    if unit:
        assert f"is in '{unit}' (1 s^-1 rad): the drive's encoder reads an angle in rad" in line
    else:
        assert "causality 'local'" in line


def test_an_integer_start_value_beyond_32_bits_is_one_line(fmus, tmp_path, capsys):
    plant = plant_file(tmp_path, fmus["maxwell_slip"], "maxwell_slip", parameters={"nElem": 2 ** 32 + 2})
    line = demo_error(tmp_path, capsys, plant)
    assert "key 'fmu.parameters.nElem'" in line and "Integer (32 bits): 4294967298 is out of its range" in line


def test_a_name_yaml_reads_as_a_boolean_says_to_quote_it(fmus, tmp_path, capsys):
    plant = plant_file(tmp_path, fmus["backlash_karnopp"], "backlash_karnopp")
    text = open(plant, encoding="utf-8").read().replace("output: q_m", "output: on")
    open(plant, "w", encoding="utf-8").write(text)
    line = demo_error(tmp_path, capsys, plant)
    assert "key 'fmu.output'" in line and "got True" in line and "quote the name" in line


def test_quotes_and_backslashes_in_the_plant_files_path_reach_drive_sim(fmus, tmp_path, capsys):
    """drive_sim only prints the plant file's and the variables' names: a path with a double
    quote and a backslash is no reason to refuse it (shown as ' and /)."""
    odd = tmp_path / 'the "new" stage\\2'
    odd.mkdir()
    params = dict(foreign.FOREIGN["maxwell_slip"]["parameters"], failMode=1, failTime=0.0)
    plant = plant_file(odd, fmus["maxwell_slip"], "maxwell_slip", parameters=params)
    line = demo_error(tmp_path, capsys, plant)
    shown = plant.replace('"', "'").replace("\\", "/")
    assert line.startswith(f"fftune: error: drive_sim: {shown}: FMU maxwell-slip_v2.fmu: fmi2DoStep(t = 0 s"), line


def test_a_path_from_the_home_folder_is_found(fmus, tmp_path, monkeypatch):
    """fmu.path: ~/models/... (as a shell expands it), the FMU in a folder named like a user's."""
    from fftune.host.fmu import drive_sim_text

    home = tmp_path / "home ü"
    (home / "models").mkdir(parents=True)
    shutil.copy(fmus["backlash_karnopp"], home / "models" / "stage v1.fmu")
    monkeypatch.setenv("HOME", str(home))
    plant = plant_file(tmp_path, fmus["backlash_karnopp"], "backlash_karnopp", copy=False,
                       path="~/models/stage v1.fmu")
    text, unzipdir = drive_sim_text(plant)
    assert 'path: "~/models/stage v1.fmu"' in text and 'model_identifier: "bls_cs"' in text
    assert os.path.isfile(os.path.join(unzipdir, "binaries", "linux64", "bls_cs.so"))
    assert "tolerance: 1e-05" in text            # its DefaultExperiment's


@pytest.mark.parametrize("mode,words", [
    (4, "the FMU crashed (SIGSEGV) in fmi2DoStep at t = 0 s"),
    (5, "fmi2DoStep did not return within 1 s (t = 0 s; the FMU hangs?)"),
])
def test_an_fmu_that_crashes_or_hangs_is_one_line_naming_the_function(fmus, tmp_path, capsys, mode, words):
    """A SIGSEGV inside fmi2DoStep (failMode 4) or an endless loop (5) in the trial step:
    drive_sim's line, not a bare signal or fftune's start-up timeout."""
    params = dict(foreign.FOREIGN["maxwell_slip"]["parameters"], failMode=mode, failTime=0.0)
    plant = plant_file(tmp_path, fmus["maxwell_slip"], "maxwell_slip", parameters=params)
    line = demo_error(tmp_path, capsys, plant)
    assert line.startswith(f"fftune: error: drive_sim: {plant}: FMU maxwell-slip_v2.fmu: "), line
    assert words in line, line


@pytest.mark.parametrize("mode,words", [
    (5, "fmi2DoStep did not return within 1 s (t = 0.3"),    # (a crash mid-run takes the same path: checked by hand, not here, for time)
])
def test_an_fmu_that_hangs_mid_run_stops_the_run_with_its_line(fmus, tmp_path, capsys, mode, words):
    params = dict(foreign.FOREIGN["maxwell_slip"]["parameters"], failMode=mode, failTime=0.3)
    plant = plant_file(tmp_path, fmus["maxwell_slip"], "maxwell_slip", parameters=params)
    out = tmp_path / "out"
    code = main(["demo", "--config", small_demo_config(tmp_path), "--plant", plant, "--out", str(out),
                 "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("fftune: error: "), err
    assert f"; drive_sim: {plant}: FMU maxwell-slip_v2.fmu: {words}" in err[0], err[0]


def test_nested_start_values_are_structured_names(fmus, tmp_path):
    """parameters: {friction: {Fc: ...}} is friction.Fc (FMI's structured naming); an unknown
    nested name is named in full."""
    from fftune.analysis.errors import FftuneError
    from fftune.host.fmu import drive_sim_text

    nested = {"friction": {"Fc": 5.0e-3, "Fs": 8.0e-3}, "nSub": 12}
    text, _ = drive_sim_text(plant_file(tmp_path, fmus["stribeck_stage"], "stribeck_stage", parameters=nested))
    assert 'p0_name: "friction.Fc"' in text and "p0_vr: 11" in text and "p0_value: 0.005" in text
    assert 'p1_name: "friction.Fs"' in text and "p1_vr: 12" in text
    assert 'p2_name: "nSub"' in text and 'p2_type: "integer"' in text and "p2_value: 12.0" in text
    with pytest.raises(FftuneError, match=r"key 'fmu.parameters.friction.Fk': .* no variable 'friction.Fk'"):
        drive_sim_text(plant_file(tmp_path, fmus["stribeck_stage"], "stribeck_stage",
                                  parameters={"friction": {"Fk": 1.0e-3}}))


@pytest.mark.parametrize("unit,definition,refused", [
    ("Winkel", '<BaseUnit rad="1" factor="0.017453292519943295"/>', "'Winkel' (0.0174533 rad)"),
    ("deg", None, "'deg'"),
    ("radian", '<BaseUnit rad="1"/>', None),
    ("Bogenmass", None, None),                # (a name fftune cannot tell: taken as rad)
])
def test_an_output_unit_is_judged_by_its_definition_else_its_name(fmus, tmp_path, unit, definition, refused):
    from fftune.analysis.errors import FftuneError
    from fftune.host.fmu import drive_sim_text

    def edit(m):
        xml = m["modelDescription.xml"].decode()
        xml = xml.replace('<ScalarVariable name="phi[1]" valueReference="1" causality="output"><Real unit="rad" '
                          'displayUnit="deg"/>', f'<ScalarVariable name="phi[1]" valueReference="1" '
                          f'causality="output"><Real unit="{unit}"/>')
        if definition:
            xml = xml.replace("<UnitDefinitions>", f'<UnitDefinitions><Unit name="{unit}">{definition}</Unit>')
        m["modelDescription.xml"] = xml.encode()
    fmu = foreign.rezip(fmus["maxwell_slip"], tmp_path / f"unit {unit}.fmu", edit)
    plant = plant_file(tmp_path, fmu, "maxwell_slip")
    if refused:
        with pytest.raises(FftuneError, match=r"key 'fmu.output': variable 'phi\[1\]' .* is in "
                                              + re.escape(refused)):
            drive_sim_text(plant)
    else:
        text, _ = drive_sim_text(plant)
        assert 'output: "phi[1]"' in text


def test_an_fmu_instantiable_once_per_process_restarts_by_reset(fmus, tmp_path):
    """ep-stage.fmu (canBeInstantiatedOnlyOncePerProcess, embedded code: its second
    fmi2Instantiate fails): drive_sim's trial step and an NMT reset go through fmi2Reset of
    the one instance; the run after the reset repeats the first run's samples."""
    import time

    import numpy as np

    from fftune.host.drive import BusOptions, DriveClient
    from fftune.host.fmu import drive_sim_text
    from fftune.host.sim import start_drive_sim
    from host_fixtures import EDS

    plant = plant_file(tmp_path, fmus["elastoplastic"], "elastoplastic")
    data = yaml.safe_load(open(plant, encoding="utf-8"))
    data["controller"] = {"kp": 0.0, "kd": 0.0}
    open(plant, "w", encoding="utf-8").write(yaml.safe_dump(data, allow_unicode=True))
    assert "once_per_process: 1" in drive_sim_text(plant)[0]
    req = {"exc_kind": 1, "exc_inject": 1, "exc_amplitude": 0.35, "exc_offset": 0.04, "exc_period": 1024,
           "exc_sine_cycles": 2, "exc_settle_periods": 0, "exc_record_periods": 1}
    sim = start_drive_sim(plant, log_path=str(tmp_path / "drive_sim.log"))
    try:
        with DriveClient(BusOptions(port=sim.port, host=sim.host, eds=EDS), progress=False, heartbeat_ms=250) as d:
            d.enable()
            first = np.asarray(d.run(req, signals=("motor_angle",)).signals["motor_angle"])
            d.node.nmt.state = "RESET"
            time.sleep(0.3)
            d.write(0x1016, 1, (127 << 16) | 1000)   # the reset cleared the consumer: re-arm it
            d.enable()
            reset = np.asarray(d.run(req, signals=("motor_angle",)).signals["motor_angle"])
    finally:
        sim.stop()
    assert np.max(np.abs(first)) > 0.05 and abs(first[-1]) > 0.01      # it moved and stayed displaced
    np.testing.assert_array_equal(reset, first)


def test_two_axes_cannot_share_an_fmu_instantiable_once_per_process(fmus, tmp_path):
    from fftune.analysis.errors import FftuneError
    from fftune.host.sim import start_drive_sim

    plant = plant_file(tmp_path, fmus["elastoplastic"], "elastoplastic")
    with pytest.raises(FftuneError) as info:
        start_drive_sim(plant, node_id=1, extra=["--axis", f"1:{plant}", "--axis", f"2:{plant}"],
                        log_path=str(tmp_path / "drive_sim.log"))
    line = str(info.value)
    assert line.startswith(f"drive_sim: {plant}: FMU ep-stage.fmu: another axis of this drive_sim runs it"), line
    assert "canBeInstantiatedOnlyOncePerProcess" in line and "\n" not in line
