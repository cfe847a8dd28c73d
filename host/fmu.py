"""Plant files that name an FMI plant model (FMU) instead of the built-in plant (docs/fmu.md).

A plant file with an ``fmu:`` section::

    fmu:
      path: models/stage.fmu        # FMI 2.0 or 3.0 co-simulation; relative: beside the plant file,
                                    # else from the working directory; ~ is the home folder
      input: u                      # Real (FMI 3.0: Float64), causality input: the drive's output [V]
      output: theta1                # Real, causality output: what the encoder reads [rad]
      load_output: theta2           # optional: the load encoder (default: output)
      parameters: {Fc: 0.0058}      # optional: start values set at instantiation (nested
                                    # keys are structured names: {friction: {Fc: 1}} = friction.Fc)
    sensor: {counts_per_rev: 2000, noise_std: 0.0, seed: 1}
    truth: {kfc_v: 0.1157}          # optional: what a report compares K_fc* with [V]
    drive: {...}                    # optional, as in configs/plant_twomass.yaml
    controller: {...}               # optional, as in configs/plant_twomass.yaml

:func:`drive_sim_plant` checks it against the FMU's modelDescription.xml (read by FMPy, the
reference for it), unpacks the FMU once into a cache folder keyed by its content and writes
drive_sim's view of the file there (the two-level YAML subset, with value references;
firmware_sim/port/fmu_plant.h). A plant file without ``fmu:`` is passed on unchanged.
Every problem is one :class:`FftuneError` naming the plant file, the FMU and the key or
variable.
"""
import hashlib
import math
import os
import platform
import shutil
import tempfile
import zipfile

from fftune.analysis.errors import FftuneError

SECTIONS = ("fmu", "sensor", "truth", "drive", "controller")
FMU_KEYS = ("path", "input", "output", "load_output", "parameters")
SENSOR_KEYS = ("counts_per_rev", "noise_std", "seed")
TRUTH_KEYS = ("kfc_v", "kv_v", "ks_v")
PARAMS_MAX = 32          # firmware_sim/port/fmu_plant.h FMUP_PARAMS_MAX
STRING_MAX = 511         # FMUP_STR - 1
# ELF e_machine of the machines drive_sim is built on (binaries/linux64 of FMI 2.0)
_ELF_MACHINES = {62: "x86_64", 183: "aarch64", 3: "i386", 40: "arm", 243: "riscv", 8: "mips", 21: "ppc64"}
_THIS_MACHINE = {"x86_64": 62, "amd64": 62, "aarch64": 183, "arm64": 183}


def read_plant_file(path):
    """The plant file as a dict (one FftuneError line if it is no YAML mapping)."""
    from fftune.host.config import read_yaml

    data = read_yaml(path, "plant configuration")
    if not isinstance(data, dict):
        raise FftuneError(f"plant configuration {path}: expected sections of key: value")
    return data


def is_fmu_plant(path):
    """True if the plant file at ``path`` names an FMU (has an ``fmu:`` section). A file
    that cannot be read is no FMU plant here (drive_sim names its problem)."""
    try:
        return "fmu" in read_plant_file(path)
    except FftuneError:
        return False


def overrides_note(path, where):
    """The note said when built-in plant overrides meet an FMU plant file."""
    return (f"note: {where}: the plant {path} is an FMU; overrides of the built-in plant do not "
            f"apply to it (its values are the FMU's fmu.parameters)")


def cache_root():
    """Where FMUs are unpacked: $FFTUNE_FMU_CACHE, else $XDG_CACHE_HOME/fftune/fmu, else
    ~/.cache/fftune/fmu (one folder per FMU content, reused)."""
    root = os.environ.get("FFTUNE_FMU_CACHE")
    if root:
        return root
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "fftune", "fmu")


def _err(plant, key, msg):
    return FftuneError(f"{plant}: key '{key}': {msg}")


def _fmu_file(plant, text):
    if not isinstance(text, str) or not text:
        raise _err(plant, "fmu.path", f"expected the FMU's file name, got {text!r}")
    text = os.path.expanduser(text)          # ~/models/stage.fmu, as a shell would
    if os.path.isabs(text):
        cands = [text]
    else:
        cands = [os.path.join(os.path.dirname(os.path.abspath(plant)), text), os.path.abspath(text)]
    for c in cands:
        if os.path.isfile(c):
            return c
        if os.path.isdir(c):
            raise _err(plant, "fmu.path", f"{text} is a directory: name the .fmu file (a zip archive)")
    raise _err(plant, "fmu.path", f"FMU file not found: {text} (relative names: beside the plant file, "
                                  f"else from the working directory; the example FMUs: make -C firmware_sim fmu)")


def _unpack(plant, fmu, root):
    """Unpack ``fmu`` into root/<sha256>/fmu once (a fresh copy when missing); returns the
    folder of its content."""
    h = hashlib.sha256()
    with open(fmu, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    key = h.hexdigest()[:24]
    dest = os.path.join(root, key, "fmu")
    if os.path.isfile(os.path.join(dest, "modelDescription.xml")):
        return dest
    if not zipfile.is_zipfile(fmu):
        raise FftuneError(f"{plant}: FMU {fmu}: not an FMU (not a zip archive)")
    os.makedirs(os.path.join(root, key), exist_ok=True)
    tmp = tempfile.mkdtemp(prefix="unpack-", dir=os.path.join(root, key))
    try:
        with zipfile.ZipFile(fmu) as z:
            for info in z.infolist():
                target = os.path.realpath(os.path.join(tmp, info.filename))
                if not target.startswith(os.path.realpath(tmp) + os.sep):
                    raise FftuneError(f"{plant}: FMU {fmu}: member {info.filename!r} points outside the archive")
            z.extractall(tmp)
        if not os.path.isfile(os.path.join(tmp, "modelDescription.xml")):
            raise FftuneError(f"{plant}: FMU {fmu}: no modelDescription.xml in the archive")
        try:
            os.replace(tmp, dest)
        except OSError:
            if not os.path.isdir(dest):   # (another process unpacked it at the same time: keep that)
                raise
    except zipfile.BadZipFile as exc:
        raise FftuneError(f"{plant}: FMU {fmu}: not a readable zip archive ({exc})") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return dest


def _binary_dir(version):
    """The FMU's folder of this platform's binary: FMI 2.0 linux64, FMI 3.0 <arch>-linux."""
    if version == 2:
        return "linux64"
    arch = {"amd64": "x86_64", "arm64": "aarch64"}.get(platform.machine().lower(), platform.machine().lower())
    return f"{arch}-linux"


def _check_binary(plant, fmu, unzipdir, mid, version=2):
    bdir_name = _binary_dir(version)
    rel = f"binaries/{bdir_name}/{mid}.so"
    so = os.path.join(unzipdir, "binaries", bdir_name, mid + ".so")
    if not os.path.isfile(so):
        bdir = os.path.join(unzipdir, "binaries")
        # platforms with a file in their folder (zip tools keep empty folders: not a binary)
        have = sorted(d for d in os.listdir(bdir) if os.path.isdir(os.path.join(bdir, d))
                      and any(files for _, _, files in os.walk(os.path.join(bdir, d)))) if os.path.isdir(bdir) else []
        if bdir_name in have:
            raise FftuneError(f"{plant}: FMU {fmu}: no {rel} (model identifier {mid}); binaries/{bdir_name} holds "
                              f"{', '.join(sorted(os.listdir(os.path.join(bdir, bdir_name)))) or 'nothing'}")
        if os.path.isdir(os.path.join(unzipdir, "sources")):
            hint = " (a source FMU: build its binary first, e.g. with fmpy.build.build_platform_binary)"
        else:
            hint = ""
        raise FftuneError(f"{plant}: FMU {fmu}: no binary for this platform ({bdir_name}, {rel}); the FMU has "
                          f"{', '.join(have) if have else 'no binaries'}{hint}")
    with open(so, "rb") as fh:
        head = fh.read(20)
    if len(head) < 20 or head[:4] != b"\x7fELF":
        raise FftuneError(f"{plant}: FMU {fmu}: {rel} is not a Linux shared library (no ELF header)")
    bits = {1: 32, 2: 64}.get(head[4])
    machine = int.from_bytes(head[18:20], "little" if head[5] == 1 else "big")
    want = _THIS_MACHINE.get(platform.machine().lower())
    if bits != 64 or (want is not None and machine != want):
        name = _ELF_MACHINES.get(machine, f"machine {machine}")
        raise FftuneError(f"{plant}: FMU {fmu}: {rel} is a {bits}-bit {name} binary; this is a 64-bit "
                          f"{platform.machine()} machine (binary for another platform)")


def _variable(plant, fmu, md, key, name, causalities, types=("Real",)):
    if isinstance(name, bool) or name is None:
        raise _err(plant, key, f"expected a variable name of {fmu}, got {name!r} (YAML reads on, off, yes, no, "
                               f"true, false, null as such: quote the name, e.g. 'on')")
    if not isinstance(name, str) or not name:
        raise _err(plant, key, f"expected a variable name of {fmu}, got {name!r}")
    by_name = {v.name: v for v in md.modelVariables}
    v = by_name.get(name)
    if v is None:
        near = [n for n in by_name if n.lower() == name.lower()]
        extra = f" (did you mean {near[0]!r}?)" if near else ""
        have = [n for n, x in by_name.items() if x.causality in causalities][:12]
        raise _err(plant, key, f"FMU {fmu} has no variable {name!r}{extra}; its {'/'.join(causalities)} "
                               f"variables: {', '.join(have) or 'none'}")
    if v.causality not in causalities:
        raise _err(plant, key, f"variable {name!r} of FMU {fmu} has causality {v.causality!r}; "
                               f"needed: {' or '.join(causalities)}")
    if v.type not in types:
        raise _err(plant, key, f"variable {name!r} of FMU {fmu} is of type {v.type}; needed: {'/'.join(types)}")
    if getattr(v, "dimensions", None):
        raise _err(plant, key, f"variable {name!r} of FMU {fmu} is an array; needed: a scalar")
    return v


def _flatten(values, prefix=""):
    """Nested start values as structured names: {friction: {Fc: 1}} -> {'friction.Fc': 1}
    (FMI's structured naming convention; a dotted key stays as it is)."""
    flat = {}
    for k, v in values.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            flat.update(_flatten(v, name + "."))
        else:
            flat[name] = v
    return flat


def _c_string(plant, what, text):
    """A string drive_sim uses as it is (the unpack folder, the model identifier, the GUID)."""
    if (len(text.encode("utf-8")) > STRING_MAX or any(ch in text for ch in '"\\')
            or any(ord(ch) < 0x20 for ch in text)):
        raise FftuneError(f"{plant}: {what} {text[:80]!r}: drive_sim takes at most {STRING_MAX} bytes (UTF-8) "
                          f"without quotes, backslashes or control characters")
    return f'"{text}"'


def _c_label(text):
    """A name drive_sim only prints in its messages (the plant file, the FMU file, variable
    names): a double quote shown as ', a backslash as /, a control character as ?, cut to
    STRING_MAX bytes (UTF-8) with '...' -- never a reason to refuse the file."""
    out = "".join("'" if ch == '"' else "/" if ch == "\\" else "?" if ord(ch) < 0x20 else ch for ch in str(text))
    if len(out.encode("utf-8")) > STRING_MAX:
        while len(out.encode("utf-8")) > STRING_MAX - 3:
            out = out[:-1]
        out += "..."
    return f'"{out}"'


def _unit(v):
    """A variable's declared unit (its own, else its declared type's), None if none."""
    unit = getattr(v, "unit", None)
    if unit is None and getattr(v, "declaredType", None) is not None:
        unit = getattr(v.declaredType, "unit", None)
    return unit


# units that are surely no angle in rad (a unit fftune cannot tell is taken as rad)
_NOT_RAD = {"deg", "degree", "degrees", "°", "rev", "r", "turn", "grad", "gon", "mrad", "urad", "arcmin", "arcsec",
            "rad/s", "deg/s", "rpm", "rev/min", "1/min", "m", "mm", "um", "m/s", "mm/s", "inc", "counts"}


def _not_rad(md, unit):
    """Why ``unit`` is surely not rad (its name, or its UnitDefinitions entry: a factor or an
    offset, other base units), else None (rad, no unit, or a unit fftune cannot tell)."""
    if not unit:
        return None
    base = next((u.baseUnit for u in (getattr(md, "unitDefinitions", None) or []) if u.name == unit), None)
    if base is not None:
        exps = [(k, getattr(base, k)) for k in ("kg", "m", "s", "A", "K", "mol", "cd", "rad") if getattr(base, k)]
        scaled = base.factor != 1.0 or base.offset != 0.0
        if exps == [("rad", 1)] and not scaled:
            return None
        if exps:                    # (a unit declared without a BaseUnit tells nothing: by its name)
            text = " ".join(f"{k}^{e}" if e != 1 else k for k, e in exps)
            return f"{unit!r} ({base.factor:g} {text}{f' + {base.offset:g}' if base.offset else ''})"
    return repr(unit) if unit.strip().lower() in _NOT_RAD else None


def _limits(v):
    """A variable's declared (min, max) as floats (its own attributes, else its declared
    type's; None where not declared)."""
    def one(attr):
        text = getattr(v, attr, None)
        if text is None and getattr(v, "declaredType", None) is not None:
            text = getattr(v.declaredType, attr, None)
        try:
            return None if text is None else float(text)
        except (TypeError, ValueError):
            return None
    return one("min"), one("max")


def _default_tolerance(md):
    """The FMU's DefaultExperiment tolerance (positive, finite), else None: drive_sim passes it
    to fmi2SetupExperiment / fmi3EnterInitializationMode as FMPy's simulate_fmu does, so the
    FMU's own solver runs as it does under FMPy."""
    try:
        tol = float(md.defaultExperiment.tolerance)
    except (AttributeError, TypeError, ValueError):
        return None
    return tol if math.isfinite(tol) and tol > 0 else None


def _numbers(plant, section, values, keys):
    if values is None:
        return {}
    if not isinstance(values, dict):
        raise _err(plant, section, f"expected {{key: number}}, got {values!r}")
    for k, v in values.items():
        if keys is not None and k not in keys:
            raise _err(plant, f"{section}.{k}", f"unknown key (expected one of {', '.join(keys)})")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise _err(plant, f"{section}.{k}", f"expected a finite number, got {v!r}")
    return values


def drive_sim_text(plant, cache=None):
    """drive_sim's plant file for the FMU plant file ``plant`` (checked; the FMU unpacked
    under ``cache``, default :func:`cache_root`). Returns (text, unpack folder)."""
    from fmpy import read_model_description

    data = read_plant_file(plant)
    for section in data:
        if section not in SECTIONS:
            hint = (" (the built-in plant's section: an FMU plant's values are its fmu.parameters)"
                    if section in ("plant", "drift") else "")
            raise _err(plant, section, f"unknown section next to 'fmu'{hint}; expected {', '.join(SECTIONS)}")
    f = data["fmu"]
    if not isinstance(f, dict):
        raise _err(plant, "fmu", f"expected path, input, output (and parameters), got {f!r}")
    for k in f:
        if k not in FMU_KEYS:
            raise _err(plant, f"fmu.{k}", f"unknown key (expected {', '.join(FMU_KEYS)})")
    for k in ("path", "input", "output"):
        if k not in f:
            raise _err(plant, f"fmu.{k}", "missing")
    fmu = _fmu_file(plant, f["path"])
    shown = f["path"]
    unzipdir = _unpack(plant, fmu, cache or cache_root())
    try:
        md = read_model_description(unzipdir, validate=False)
    except Exception as exc:  # FMPy raises plain Exceptions (XML, schema, version) pylint: disable=broad-except
        msg = " ".join(str(exc).split()) or type(exc).__name__
        raise FftuneError(f"{plant}: FMU {shown}: modelDescription.xml: {msg}") from None
    if md.fmiVersion not in ("2.0", "3.0"):
        raise FftuneError(f"{plant}: FMU {shown}: FMI {md.fmiVersion}: drive_sim co-simulates FMI 2.0 and 3.0 "
                          f"FMUs (co-simulation; docs/fmu.md)")
    if md.coSimulation is None:
        raise FftuneError(f"{plant}: FMU {shown}: model exchange only: drive_sim co-simulates FMI 2.0 / 3.0 "
                          f"co-simulation FMUs (export the model for co-simulation; docs/fmu.md)")
    version = int(md.fmiVersion[0])
    mid = md.coSimulation.modelIdentifier
    _check_binary(plant, shown, unzipdir, mid, version)
    real = ("Real",) if version == 2 else ("Float64",)
    vin = _variable(plant, shown, md, "fmu.input", f["input"], ("input",), real)
    vout = _variable(plant, shown, md, "fmu.output", f["output"], ("output",), real)
    vload = None
    if f.get("load_output") is not None:
        vload = _variable(plant, shown, md, "fmu.load_output", f["load_output"], ("output",), real)
    for key, v in (("fmu.output", vout), ("fmu.load_output", vload)):
        why = _not_rad(md, _unit(v)) if v is not None else None
        if why:
            raise _err(plant, key, f"variable {v.name!r} of FMU {shown} is in {why}: the drive's encoder reads "
                                   f"an angle in rad (export the angle in rad)")
    params = f.get("parameters") or {}
    if not isinstance(params, dict):
        raise _err(plant, "fmu.parameters", f"expected {{variable: value}}, got {params!r}")
    params = _flatten(params)
    if len(params) > PARAMS_MAX:
        raise _err(plant, "fmu.parameters", f"{len(params)} values: drive_sim sets at most {PARAMS_MAX}")
    plist = []
    for name, value in params.items():
        key = f"fmu.parameters.{name}"
        v = _variable(plant, shown, md, key, str(name), ("parameter", "input"),
                      ("Real", "Integer", "Boolean") if version == 2 else ("Float64", "Int32", "Boolean"))
        if v.variability == "constant" or v.initial == "calculated":
            raise _err(plant, key, f"variable {name!r} of FMU {shown} cannot be set "
                                   f"(variability {v.variability}, initial {v.initial})")
        if v.type == "Boolean":
            if not isinstance(value, bool):
                raise _err(plant, key, f"variable {name!r} is Boolean: expected true or false, got {value!r}")
            value = float(value)
        elif isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _err(plant, key, f"expected a number, got {value!r}")
        elif not math.isfinite(value):
            raise _err(plant, key, f"expected a finite number, got {value!r}")
        elif v.type in ("Integer", "Int32") and value != int(value):
            raise _err(plant, key, f"variable {name!r} is Integer: expected a whole number, got {value!r}")
        elif v.type in ("Integer", "Int32") and not -2 ** 31 <= value < 2 ** 31:
            raise _err(plant, key, f"variable {name!r} is Integer (32 bits): {value!r} is out of its range")
        if v.type != "Boolean":
            lo, hi = _limits(v)
            if (lo is not None and value < lo) or (hi is not None and value > hi):
                raise _err(plant, key, f"{value!r} is outside the range variable {name!r} of FMU {shown} declares "
                                       f"(min {lo if lo is not None else '-inf'}, max {hi if hi is not None else 'inf'})")
        kind = {"Real": "real", "Float64": "real", "Integer": "integer", "Int32": "integer"}.get(v.type, "boolean")
        plist.append((str(name), v.valueReference, kind, float(value)))
    sensor = _numbers(plant, "sensor", data.get("sensor"), SENSOR_KEYS)
    truth = _numbers(plant, "truth", data.get("truth"), TRUTH_KEYS)
    lines = [f"# drive_sim's view of {plant} (written by fftune: docs/fmu.md)"]
    for section, values in (("drive", _numbers(plant, "drive", data.get("drive"), None)),
                            ("controller", _numbers(plant, "controller", data.get("controller"), None)),
                            ("sensor", sensor), ("truth", truth)):
        if values:
            lines.append(f"{section}:")
            lines += [f"  {k}: {v!r}" for k, v in values.items()]
    lines += ["fmu:",
              f"  source: {_c_label(plant)}",
              f"  path: {_c_label(shown)}",
              f"  fmi_version: {version}",
              f"  unzipdir: {_c_string(plant, 'unpack folder', unzipdir)}",
              f"  model_identifier: {_c_string(plant, 'model identifier', mid)}",
              f"  guid: {_c_string(plant, 'GUID', md.guid or '')}",
              f"  input: {_c_label(vin.name)}",
              f"  input_vr: {vin.valueReference}",
              f"  output: {_c_label(vout.name)}",
              f"  output_vr: {vout.valueReference}"]
    if vload is not None:
        lines += [f"  load_output: {_c_label(vload.name)}",
                  f"  load_output_vr: {vload.valueReference}"]
    tol = _default_tolerance(md)
    if tol is not None:
        lines.append(f"  tolerance: {tol!r}")
    if md.coSimulation.canBeInstantiatedOnlyOncePerProcess:
        lines.append("  once_per_process: 1")       # (one instance, restarted by fmi2Reset)
    for i, (name, vr, typ, value) in enumerate(plist):
        lines += [f"  p{i}_name: {_c_label(name)}", f"  p{i}_vr: {vr}",
                  f'  p{i}_type: "{typ}"', f"  p{i}_value: {value!r}"]
    return "\n".join(lines) + "\n", unzipdir


def drive_sim_plant(plant, cache=None):
    """The plant file drive_sim reads for ``plant``: ``plant`` itself (built-in plant), or
    for an FMU plant file the checked view written beside the unpacked FMU (named by its
    content, so repeated and concurrent runs share it)."""
    if not is_fmu_plant(plant):
        return plant
    text, unzipdir = drive_sim_text(plant, cache)
    digest = hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]
    path = os.path.join(os.path.dirname(unzipdir), f"drive_sim-{digest}.yaml")
    if not os.path.isfile(path):
        fd, tmp = tempfile.mkstemp(prefix=".drive_sim-", suffix=".yaml", dir=os.path.dirname(unzipdir))
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.replace(tmp, path)
    return path
