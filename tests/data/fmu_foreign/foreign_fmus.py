"""Build the foreign FMUs of this folder the way an outside engineer would: a hand-written
FMI 2.0 co-simulation slave (common/cs2.c, not fftune's firmware_sim/fmu/fmu_slave.c) and a
hand-written modelDescription.xml with <SourceFiles>, compiled by FMPy's own CMake project
(``fmpy.build.build_platform_binary``) and zipped by ``fmpy.util.create_zip_archive``.

``build(name)`` returns the path of ``<name>``'s FMU, built once into a cache folder named by
the sources' content (``firmware_sim/build/fmu_foreign/<sha256>/``; a changed source builds
anew). ``FOREIGN`` says what each FMU is and what its truth is (docs/fmu.md).
"""
import hashlib
import os
import shutil
import sys
import tempfile
import zipfile

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(os.path.dirname(HERE)))
CACHE = os.path.join(REPO, "firmware_sim", "build", "fmu_foreign")

# name -> the FMU file's name (not the model identifier), extras, the plant file's fmu: keys,
# truth [V] = sliding friction level / km
FOREIGN = {
    "stribeck_stage": {
        "file": "Stribeck stage (ü).fmu",
        "win64": True,                     # ships binaries/win64 too (another exporter's habit)
        "input": "drive.u", "output": "body.phi", "load_output": "load.phi",
        "parameters": {"friction.Fc": 6.0e-3, "friction.Fs": 9.0e-3, "nSub": 16, "viscous": True},
        "truth": {"kfc_v": 6.0e-3 / 0.05, "kv_v": 2.0e-4 / 0.05, "ks_v": 9.0e-3 / 0.05},
        "law": "two-mass, smooth Stribeck (tanh) + viscous at the motor",
    },
    "maxwell_slip": {
        "file": "maxwell-slip_v2.fmu",
        "input": "u_cmd", "output": "phi[1]", "load_output": "phi[2]",
        "parameters": {"tau_i": 5.0e-4, "delay": True, "nElem": 3},
        "truth": {"kfc_v": (1.5e-3 + 2.0e-3 + 2.3e-3) / 0.05},
        "law": "Maxwell-slip (3 elements from resources/elements.csv) + viscous, current loop lag, one-step delay",
    },
    "backlash_karnopp": {
        "file": "BacklashStage.fmu",
        "input": "u", "output": "q_m", "load_output": "q_l",
        "parameters": {"Fc": 5.5e-3, "Fs": 7.0e-3, "gap": 1.0e-3, "warnOnImpact": True},
        "truth": {"kfc_v": 5.5e-3 / 0.05, "ks_v": 7.0e-3 / 0.05},
        "law": "Karnopp stick-slip Coulomb at the motor, backlash to the load",
    },
    "elastoplastic": {
        "file": "ep-stage.fmu",
        "input": "Motor.u", "output": "Motor.phi", "load_output": "Load.phi",
        "parameters": {"friction": {"Fc": 6.2e-3, "Fs": 8.5e-3}, "nSub": 40},
        "truth": {"kfc_v": 6.2e-3 / 0.05, "kv_v": 1.5e-4 / 0.05, "ks_v": 8.5e-3 / 0.05},
        "law": "elasto-plastic (Dupont 2002) with Stribeck and viscous; one instance per process",
    },
}


def _digest(name):
    import fmpy

    h = hashlib.sha256(fmpy.__version__.encode())
    for folder in ("common", name):
        base = os.path.join(HERE, folder)
        for root, dirs, files in os.walk(base):
            dirs.sort()
            for f in sorted(files):
                p = os.path.join(root, f)
                h.update(os.path.relpath(p, HERE).encode())
                with open(p, "rb") as fh:
                    h.update(fh.read())
    h.update(repr(FOREIGN[name]).encode())
    return h.hexdigest()[:20]


def unpacked_tree(name, dest):
    """The source FMU's folder (modelDescription.xml, sources/, resources/) in ``dest``."""
    src = os.path.join(HERE, name)
    os.makedirs(os.path.join(dest, "sources"))
    shutil.copy(os.path.join(src, "modelDescription.xml"), dest)
    for folder in (os.path.join(HERE, "common"), src):
        for f in sorted(os.listdir(folder)):
            if f.endswith((".c", ".h")):
                shutil.copy(os.path.join(folder, f), os.path.join(dest, "sources", f))
    if os.path.isdir(os.path.join(src, "resources")):
        shutil.copytree(os.path.join(src, "resources"), os.path.join(dest, "resources"))


def build(name, cache=CACHE):
    """The FMU ``name`` (a key of FOREIGN), built once per content; returns its path."""
    from fmpy.build import build_platform_binary
    from fmpy.util import create_zip_archive

    spec = FOREIGN[name]
    folder = os.path.join(cache, _digest(name))
    fmu = os.path.join(folder, spec["file"])
    if os.path.isfile(fmu):
        return fmu
    os.makedirs(cache, exist_ok=True)
    work = tempfile.mkdtemp(prefix=f".{name}-", dir=cache)
    try:
        tree = os.path.join(work, "unzipped")
        unpacked_tree(name, tree)
        os.makedirs(os.path.join(work, "cmake"))
        path = os.environ.get("PATH", "")
        os.environ["PATH"] = os.path.dirname(sys.executable) + os.pathsep + path   # pip's cmake, if any
        log = os.path.join(work, "build.log")
        saved = [os.dup(1), os.dup(2)]
        try:
            sys.stdout.flush()
            sys.stderr.flush()
            with open(log, "wb") as fh:                  # cmake's output: into the log, shown on failure
                os.dup2(fh.fileno(), 1)
                os.dup2(fh.fileno(), 2)
                try:
                    build_platform_binary(tree, build_dir=os.path.join(work, "cmake"))
                finally:
                    os.dup2(saved[0], 1)
                    os.dup2(saved[1], 2)
        except Exception as exc:
            with open(log, encoding="utf-8", errors="replace") as fh:
                tail = fh.read()[-3000:]
            raise RuntimeError(f"building {name} with FMPy's build_platform_binary failed: {exc}\n{tail}") from None
        finally:
            os.close(saved[0])
            os.close(saved[1])
            os.environ["PATH"] = path
        if spec.get("win64"):
            os.makedirs(os.path.join(tree, "binaries", "win64"))
            with open(os.path.join(tree, "binaries", "win64", "StribeckStage.dll"), "wb") as fh:
                fh.write(b"MZ" + bytes(62))        # (a placeholder: not loaded on Linux)
        os.makedirs(os.path.join(work, "out"))
        create_zip_archive(os.path.join(work, "out", spec["file"]), tree)
        try:
            os.replace(os.path.join(work, "out"), folder)
        except OSError:
            if not os.path.isfile(fmu):       # (another process built it at the same time: keep that)
                raise
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return fmu


def rezip(fmu, dest, edit):
    """``fmu`` rewritten to ``dest``: ``edit(members)`` changes the dict name -> bytes."""
    with zipfile.ZipFile(fmu) as z:
        members = {n: z.read(n) for n in z.namelist()}
    edit(members)
    with zipfile.ZipFile(dest, "w", zipfile.ZIP_DEFLATED) as z:
        for n, data in members.items():
            z.writestr(n, data)
    return str(dest)


if __name__ == "__main__":
    for n in sys.argv[1:] or FOREIGN:
        print(build(n))
