"""The processor-in-the-loop build's plant configuration: ``sim.plant`` of an fftune
configuration (configs/pil.yaml) with its ``sim.overrides`` applied, written in
drive_sim's YAML subset. The MCU build compiles exactly this file in (port/mcu/cfggen),
and drive_sim reads the same file for the determinism check.

usage: python pil_plant.py CONFIG_YAML OUT_PLANT_YAML
"""
import os
import sys

from fftune.analysis.errors import FftuneError
from fftune.host.config import load_config
from fftune.host.resources import config_path
from fftune.host.sim import DEFAULT_PLANT, derived_plant


def plant_file(cfg, config_file):
    """Path of ``sim.plant`` (default the packaged twomass set-up); ``configs/NAME`` is
    looked up relative to the configuration file's checkout, then in the package data."""
    plant = cfg["sim"]["plant"] or DEFAULT_PLANT
    if os.path.isabs(plant) or os.path.exists(plant):
        return plant
    beside = os.path.join(os.path.dirname(os.path.abspath(config_file)), "..", plant)
    if os.path.exists(beside):
        return os.path.normpath(beside)
    packaged = config_path(os.path.basename(plant))
    if os.path.exists(packaged):
        return packaged
    raise FftuneError(f"{config_file}: key 'sim.plant': {plant} not found")


def main(argv):
    if len(argv) != 3:
        print(__doc__.strip().splitlines()[-1], file=sys.stderr)
        return 2
    config_file, out = argv[1], argv[2]
    try:
        cfg = load_config(config_file)
        os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
        derived_plant(plant_file(cfg, config_file), cfg["sim"]["overrides"], out,
                      where=f"{config_file}: key 'sim.overrides'")
        print(cfg["drive"]["node_id"])
    except FftuneError as exc:
        print(f"fftune: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
