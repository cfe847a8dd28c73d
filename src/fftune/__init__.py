"""fftune: measure how nonlinear a motion system is and tune its friction feed-forward.

Subpackages
-----------
fftune.analysis
    Numerical methods on arrays (multisines, robust BLA, HOSIDF, tuning objective,
    plots); no CAN code.
fftune.host
    The CANopen host: drives a (simulated) drive through the experiments.
fftune.configs
    Package data: the object dictionary source (od.yaml), the drive's EDS generated
    from it, and the example configurations.

In the source tree the subpackages live in the top-level folders ``analysis/``,
``host/`` and ``configs/`` (mapped by ``pyproject.toml``).
"""
from importlib.metadata import PackageNotFoundError, version as _version

try:
    __version__ = _version("fftune")
except PackageNotFoundError:  # running from a tree that was never installed
    __version__ = "0+unknown"
