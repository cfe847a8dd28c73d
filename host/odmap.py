"""Parameter names of the drive, from the one source of truth ``configs/od.yaml``.

Each manufacturer entry with ``param: NAME`` gets the short alias ``name.lower()``
(``KFC`` -> ``kfc``, ``EXC_AMPLITUDE`` -> ``exc_amplitude``) beside its EDS name
(``"Controller.Coulomb feed-forward K_fc"``). The host addresses objects by (index,
sub-index) resolved from either; the drive's EDS supplies types and access.
"""
import functools
import os
from dataclasses import dataclass

import yaml

from fftune.analysis.errors import FftuneError
from fftune.host.resources import EDS_NAME, config_path

OD_YAML = config_path("od.yaml")
# Generated from od.yaml by firmware_sim/tools/odgen.py; a test keeps the copy current.
DEFAULT_EDS = config_path(EDS_NAME)

# Recorder signals in bit order (firmware_sim/core/drv.h DRV_SIG_*).
SIGNAL_BITS = {"reference": 0, "plant_input": 1, "motor_angle": 2, "load_angle": 3, "error": 4}
RUN_STATES = {0: "idle", 1: "settling", 2: "recording", 3: "done", 4: "aborted", 5: "fault"}
STOP_REASONS = {
    0: "none", 1: "abort command", 2: "host heartbeat lost", 3: "drive left OPERATION ENABLED",
    4: "recorder too small for the run", 5: "inconsistent excitation parameters",
    6: "NMT left OPERATIONAL", 7: "non-finite measurement (fault)",
    8: "controller output not finite (fault)",
    9: "statistics line above fs/2 (harmonics x sine cycles >= N/2)",
    10: "harmonic statistics asked for a run without a sine",
    11: "line statistics set-up (a line at or above N/2, N not a power of two within the "
        "table capacity, or the recorder not holding r, u, y)",
}
EXC_KINDS = {"none": 0, "sine": 1, "table": 2, "multisine": 3}
INJECT = {"reference": 0, "plant_input": 1}


@dataclass(frozen=True)
class ParamEntry:
    alias: str
    eds_name: str      # "Record.Sub name" or "Name" for a plain variable
    index: int
    subindex: int
    type: str
    access: str
    unit: str


def _entries(od):
    for obj in od.get("objects", []):
        if "sub" in obj:
            for sub in obj["sub"]:
                yield obj, sub
        else:
            yield None, obj


# libyaml's parser where PyYAML has it (the same safe constructors and resolver): od.yaml
# takes the pure-Python parser 0.13 s on a quiet machine (8x that of libyaml), 20-40x
# longer in the qemu guest, and a tune's preflight read it eleven times
_OD_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


@functools.lru_cache(maxsize=4)
def _parsed(path, mtime_ns, size):
    with open(path, "r", encoding="utf-8") as fh:
        return yaml.load(fh, Loader=_OD_LOADER)


def load_od(path=OD_YAML):
    """The object dictionary source ``path`` parsed, once per process and version of the
    file (every command reads it for its parameter map and the drive's limits). Read it,
    do not modify it: the object is shared."""
    try:
        st = os.stat(path)
        return _parsed(os.fspath(path), st.st_mtime_ns, st.st_size)
    except OSError as exc:
        raise FftuneError(f"{path}: cannot read the object dictionary source: {exc.strerror}") from None


def load_param_map(path=OD_YAML):
    """``{alias: ParamEntry}`` for every OD entry carrying ``param``."""
    od = load_od(path)
    out = {}
    for parent, entry in _entries(od):
        if "param" not in entry:
            continue
        alias = entry["param"].lower()
        if parent is not None:
            eds_name = f"{parent['name']}.{entry['name']}"
            index, sub = parent["index"], entry["sub"]
        else:
            eds_name, index, sub = entry["name"], entry["index"], 0
        out[alias] = ParamEntry(alias, eds_name, index, sub, entry["type"], entry["access"],
                                entry.get("unit", ""))
    return out


PARAMS = load_param_map()

# CiA 301 / 402 objects the host reads or writes (DriveClient: probe, heartbeats, identity,
# the CiA 402 state machine); every manufacturer object of od.yaml that is not sim_only is
# part of the profile too. docs/drive-profile.md describes them for drive vendors.
PROFILE_DOC = "docs/drive-profile.md"
STANDARD_PROFILE_OBJECTS = {
    0x1000: "Device type", 0x1008: "Manufacturer device name",
    0x100A: "Manufacturer software version", 0x1016: "Consumer heartbeat time",
    0x1017: "Producer heartbeat time", 0x1018: "Identity object",
    0x6040: "Controlword", 0x6041: "Statusword",
}


def profile_objects(path=OD_YAML):
    """The objects an fftune drive must provide: ``[(index, subindex or None, name)]``.

    ``subindex`` None stands for the object as a whole (a variable, a DOMAIN, or a record
    whose every listed sub-index is required, then given as its own entries too)."""
    od = load_od(path)
    out = [(index, None, name) for index, name in sorted(STANDARD_PROFILE_OBJECTS.items())]
    for obj in od.get("objects", []):
        if not 0x2000 <= obj["index"] <= 0x5FFF or obj.get("sim_only") \
                or obj.get("profile") == "optional":
            continue
        out.append((obj["index"], None, obj["name"]))
        for sub in obj.get("sub", []):
            if sub.get("profile") != "optional":     # e.g. 0x2000:9-11 (tune.method model only)
                out.append((obj["index"], sub["sub"], f"{obj['name']}.{sub['name']}"))
    return out


def missing_profile_objects(object_dictionary, required=None):
    """Names of the profile objects absent from a python-canopen ``ObjectDictionary``
    (``"0x2000 Controller"``, or ``"0x2010:6 Run control.Run length"`` when only a
    sub-index lacks); an absent object is named once, not with each of its sub-indices."""
    missing, absent = [], set()
    for index, sub, name in (profile_objects() if required is None else required):
        if index in absent:
            continue
        if index not in object_dictionary:
            absent.add(index)
            missing.append(f"0x{index:04X} {name}")
        elif sub is not None:
            obj = object_dictionary[index]
            if not hasattr(obj, "__contains__") or sub not in obj:
                missing.append(f"0x{index:04X}:{sub} {name}")
    return missing


def check_drive_profile(object_dictionary, eds):
    """A one-line :class:`FftuneError` if the EDS lacks objects of the fftune drive profile."""
    missing = missing_profile_objects(object_dictionary)
    if not missing:
        return
    shown = ", ".join(missing[:8]) + (f" and {len(missing) - 8} more" if len(missing) > 8 else "")
    raise FftuneError(f"EDS {eds}: not an fftune drive: it lacks {shown} (the fftune drive "
                      f"profile: objects, units and behaviour a drive must provide are listed in "
                      f"{PROFILE_DOC} of the fftune sources)")
