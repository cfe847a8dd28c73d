"""Parameter names of the drive, from the one source of truth ``configs/od.yaml``.

Each manufacturer entry with ``param: NAME`` gets the short alias ``name.lower()``
(``KFC`` -> ``kfc``, ``EXC_AMPLITUDE`` -> ``exc_amplitude``) beside its EDS name
(``"Controller.Coulomb feed-forward K_fc"``). The host addresses objects by (index,
sub-index) resolved from either; the drive's EDS supplies types and access.
"""
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


def load_param_map(path=OD_YAML):
    """``{alias: ParamEntry}`` for every OD entry carrying ``param``."""
    try:
        with open(path, "r", encoding="utf-8") as fh:
            od = yaml.safe_load(fh)
    except OSError as exc:
        raise FftuneError(f"{path}: cannot read the object dictionary source: {exc.strerror}") from None
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
