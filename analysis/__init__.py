"""fftune.analysis: numerical methods for nonlinear motion systems.

Random odd multisines, the robust Best Linear Approximation with noise and nonlinear
variances, odd/even nonlinearity detection, HOSIDFs and the friction feed-forward tuning
objective. Works on arrays from any source; imports no CAN code.
"""

from fftune import __version__  # noqa: F401  (one version: the distribution's)
