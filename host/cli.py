"""The ``fftune`` command line: one entry point, subcommands registered by modules.

Each module in ``SUBCOMMAND_MODULES`` has ``add_parser(subparsers)`` which adds its
subcommand(s) and sets ``func`` (called with the parsed args, returns an exit code).
User errors (:class:`fftune.analysis.errors.FftuneError`) are printed as one line, exit code 2.
"""
import argparse
import importlib
import signal
import sys

from fftune.analysis.errors import FftuneError

from fftune.host import __version__

# Order = order in --help.
SUBCOMMAND_MODULES = [
    "fftune.host.commands",
    "fftune.host.sim",
    "fftune.analysis.cli",
    "fftune.host.demo",
    "fftune.host.fleet",
    "fftune.host.paper",
    "fftune.host.track",
]


MAX_ERROR_CHARS = 2000


def one_line(message, max_chars=MAX_ERROR_CHARS):
    """``message`` as one terminal line: control characters a file name or a YAML key may
    carry (a newline, an escape sequence that recolours the terminal) shown escaped
    (``\\n``, ``\\x1b``), at most ``max_chars`` characters (its middle left out)."""
    text = "".join(ch if ch.isprintable() or ch == " " else repr(ch)[1:-1] for ch in str(message))
    if len(text) <= max_chars:
        return text
    half = (max_chars - 5) // 2      # (the start names the object, the end says what is wrong)
    return text[:half] + " ... " + text[-half:]


class Parser(argparse.ArgumentParser):
    """argparse's parser whose errors (a missing argument, ``--node-id abc``, an option out
    of range) are the one line of every fftune error: ``fftune: error: ...``, exit 2 (the
    usage is in ``--help``); subcommands' parsers are of this class too."""

    def error(self, message):
        sub = self.prog[len("fftune"):].strip() if self.prog.startswith("fftune") else self.prog
        self.exit(2, f"fftune: error: {sub + ': ' if sub else ''}{one_line(' '.join(str(message).split()))}\n")


def build_parser():
    parser = Parser(
        prog="fftune",
        description="Measure how nonlinear a motion system is and tune its friction feed-forward.",
    )
    parser.add_argument("--version", action="version", version=f"fftune {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMAND_MODULES:
        importlib.import_module(name).add_parser(sub)
    return parser


class Terminated(BaseException):
    """SIGTERM, raised in the main thread like KeyboardInterrupt for Ctrl-C, so that every
    ``with`` / ``finally`` runs (the drive client stops the run and disables the drive)."""


def _raise_terminated(signum, frame):
    raise Terminated()


def main(argv=None):
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:       # --help, --version (0) or the one error line (2): printed
        return exc.code if isinstance(exc.code, int) else 2
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        previous = signal.signal(signal.SIGTERM, _raise_terminated)
    except ValueError:  # not the main thread (an embedding program): its own signal handling
        previous = None
    try:
        return int(args.func(args) or 0)
    except Terminated:
        print("fftune: terminated", file=sys.stderr)
        return 143
    except FftuneError as exc:
        print(f"fftune: error: {one_line(exc)}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("fftune: interrupted", file=sys.stderr)
        return 130
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
