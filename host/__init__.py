"""fftune.host: drives a CANopen motion drive (simulated or real) through the
detect -> quantify -> tune experiments, stores captures, writes reports.

Depends on :mod:`analysis`; never the other way round.
"""

from fftune import __version__  # noqa: F401  (one version: the distribution's)
