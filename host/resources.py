"""Where the host finds its data files and the simulated drive, installed or in a checkout.

Package data (``fftune.configs``: od.yaml, the generated EDS, example configurations) is
read through :mod:`importlib.resources`, so a wheel install works as a source checkout does.
``drive_sim`` is a C program built from the checkout (``make setup``); an installed
package finds it through ``FFTUNE_DRIVE_SIM`` or a checkout it was installed from.
"""
import os
from importlib import resources
from pathlib import Path

from fftune.analysis.errors import FftuneError

EDS_NAME = "fftune_drive.eds"


def config_path(name):
    """Path of a packaged configuration file (``configs/NAME`` in the source tree)."""
    return str(resources.files("fftune.configs").joinpath(name))


def checkout_root():
    """The source checkout this package runs from (editable install), or None."""
    root = Path(__file__).resolve().parent.parent
    return root if (root / "firmware_sim" / "Makefile").is_file() else None


def drive_sim_path():
    """Path of the ``drive_sim`` executable, or a one-line error that says how to get it."""
    env = os.environ.get("FFTUNE_DRIVE_SIM")
    if env:
        if not os.path.isfile(env) or not os.access(env, os.X_OK):     # (a directory is X_OK)
            raise FftuneError(f"FFTUNE_DRIVE_SIM={env}: not an executable file")
        return env
    root = checkout_root()
    if root is not None:
        exe = root / "firmware_sim" / "build" / "drive_sim"
        if exe.is_file():
            return str(exe)
        raise FftuneError(f"{exe} not built: run `make setup` (or `make -C {root}/firmware_sim`)")
    raise FftuneError("the simulated drive (drive_sim) is not part of the installed package: "
                      "build it in a checkout (`make -C firmware_sim`) and set "
                      "FFTUNE_DRIVE_SIM=/path/to/firmware_sim/build/drive_sim")
