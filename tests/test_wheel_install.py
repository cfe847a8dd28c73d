"""The wheel as a user installs it: built from a copy of the sources, installed into a
fresh venv (no network: the dependencies come from this test run's own environment
through a .pth line, the editable install of the checkout stays invisible), then used
from a directory outside the checkout."""
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest
import yaml

from conftest import DRIVE_SIM_BIN

REPO = Path(__file__).resolve().parents[1]
SOURCES = ("pyproject.toml", "README.md", "src", "analysis", "host", "configs")


def _run(cmd, cwd, env=None, timeout=300):
    return subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout)


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(venv python, venv bin dir, wheel path, a work directory outside the checkout)."""
    root = tmp_path_factory.mktemp("wheel")
    src = root / "src"
    src.mkdir()
    # a copy: an in-tree build would leave build/ and *.egg-info in the checkout (and
    # race with another xdist worker)
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, src / name,
                            ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            shutil.copy2(REPO / name, src / name)
    dist = root / "dist"
    built = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                  "--no-index", "-q", "-w", dist, src], cwd=root)
    if built.returncode != 0:
        if "No module named" in built.stderr or "setuptools" in built.stderr.lower():
            pytest.skip(f"no network-free wheel build here (setuptools/wheel not in this "
                        f"environment): {built.stderr.strip().splitlines()[-1]}")
        pytest.fail(f"pip wheel failed:\n{built.stderr}")
    (wheel,) = dist.glob("fftune-*.whl")
    venv = root / "venv"
    made = _run([sys.executable, "-m", "venv", "--without-pip", venv], cwd=root)
    assert made.returncode == 0, made.stderr
    vpy = venv / "bin" / "python"
    vsite = Path(_run([vpy, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                      cwd=root).stdout.strip())
    # dependencies (numpy, scipy, canopen ...) from this environment, appended after the
    # venv's own site-packages; .pth files there (the checkout's editable finder) are not run
    (vsite / "zz_test_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    inst = _run([sys.executable, "-m", "pip", "--python", vpy, "install", "--no-deps",
                 "--no-index", "-q", wheel], cwd=root)
    assert inst.returncode == 0, inst.stderr
    work = root / "work"
    work.mkdir()
    return vpy, venv / "bin", wheel, work


def clean_env(**extra):
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "FFTUNE_DRIVE_SIM", "VIRTUAL_ENV")}
    env.update(extra)
    return env


def test_wheel_holds_only_the_fftune_namespace_and_its_data(installed):
    _, _, wheel, _ = installed
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/", 1)[0] for n in names}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"fftune"}
    for data in ("fftune/configs/od.yaml", "fftune/configs/fftune_drive.eds",
                 "fftune/configs/demo.yaml", "fftune/analysis/bla.py", "fftune/host/cli.py"):
        assert data in names


def test_import_from_the_venv_not_the_checkout(installed):
    vpy, _, _, work = installed
    out = _run([vpy, "-c", "import importlib.util as u, fftune, fftune.analysis as a; "
                           "print(a.__file__); "
                           "print(u.find_spec('analysis'), u.find_spec('host')); "
                           "from fftune.analysis import robust_bla, hosidf, random_odd_multisine; "
                           "print(fftune.__version__)"], cwd=work, env=clean_env())
    assert out.returncode == 0, out.stderr
    where, tops, version = out.stdout.split("\n")[:3]
    assert where.startswith(str(vpy.parent.parent)) and str(REPO) not in where
    assert tops == "None None"                    # no top-level analysis / host installed
    assert version == "0.1.0"


def test_version_and_analyze_bla_on_a_csv(installed):
    vpy, bindir, _, work = installed
    ver = _run([bindir / "fftune", "--version"], cwd=work, env=clean_env())
    assert ver.returncode == 0 and ver.stdout.strip().endswith("0.1.0"), ver.stderr
    # y = u + 0.2 u^3 on 2 realizations x 3 periods of a random odd multisine
    code = ("import numpy as np; from fftune.analysis import random_odd_multisine as r; "
            "u, _ = r(1000.0, 256, 2, k_min=1, k_max=100, rms=0.5, seed=4); "
            "u = np.repeat(u[:, None, :], 3, axis=1).reshape(-1); y = u + 0.2 * u ** 3; "
            "np.savetxt('d.csv', np.column_stack([u, y]), delimiter=',', header='u,y', "
            "comments='')")
    assert _run([vpy, "-c", code], cwd=work, env=clean_env()).returncode == 0
    out = _run([bindir / "fftune", "analyze", "bla", "d.csv", "--fs", "1000", "--period", "256",
                "--realizations", "2", "--json", "r.json"], cwd=work, env=clean_env())
    assert out.returncode == 0, out.stderr
    assert "BLA of y / u" in out.stdout and (work / "r.json").exists()


def test_demo_without_drive_sim_says_how_to_build_it(installed):
    _, bindir, _, work = installed
    out = _run([bindir / "fftune", "demo", "--out", work / "nodemo", "--no-progress"],
               cwd=work, env=clean_env())
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("fftune: error: ")
    assert "FFTUNE_DRIVE_SIM" in lines[0] and "make -C firmware_sim" in lines[0]
    assert "Traceback" not in out.stderr


@pytest.mark.skipif(not os.access(DRIVE_SIM_BIN, os.X_OK),
                    reason=f"{DRIVE_SIM_BIN} not built (make setup)")
def test_demo_with_drive_sim_from_the_environment(installed):
    _, bindir, _, work = installed
    cfg = yaml.safe_load((REPO / "configs" / "demo.yaml").read_text())
    cfg["detect"].update(rms_levels=[1.0], realizations=2)
    cfg["quantify"].update(frequencies_hz=[2.5], rms_levels=[0.5], repeats=1)
    cfg["tune"]["sweep"]["points"] = 4
    cfg["tune"]["viscous"]["enabled"] = False
    (work / "small.yaml").write_text(yaml.safe_dump(cfg))
    out = _run([bindir / "fftune", "demo", "--config", "small.yaml", "--out", work / "demo",
                "--no-progress"], cwd=work, env=clean_env(FFTUNE_DRIVE_SIM=DRIVE_SIM_BIN),
               timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "K_fc* (automated search)" in out.stdout
    results = yaml.safe_load((work / "demo" / "results.yaml").read_text())
    assert results["fftune_version"] == "0.1.0"           # the installed distribution's
    assert results["runs"]["detect"] == 2 and results["runs"]["tune"] > 0
    assert "objective" in results["tune"]
    assert (work / "demo" / "report.html").exists()
