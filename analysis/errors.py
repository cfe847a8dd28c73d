"""Errors that reach the user as one clear line (the CLI prints them, exit code 2)."""


class FftuneError(Exception):
    """A user-facing error: bad input, bad configuration, unreachable device.

    The message must name the problem and the object (file, line, key, column ...).
    The command-line front end prints ``fftune: error: <message>`` and exits with
    ``exit_code`` instead of a traceback.
    """

    exit_code = 2


class InputError(FftuneError, ValueError):
    """Measured data or analysis options that cannot be used as given."""


class OutputExistsError(FftuneError, FileExistsError):
    """An output file (e.g. a capture) already exists and is never overwritten."""
