"""`main(argv)`: parse, run one command, and turn expected failures into one error line.

Each command is a module with `register(subparsers)`, which adds its parser and sets `run`, and
`run(args) -> int`. The modules import the library only inside `run`, so `cldyn --help` is fast and
lists the MuJoCo commands even where the `[mujoco]` extra is missing (running one then says so).
"""

import argparse
import sys

import equinox as eqx

from .. import CheckpointError, NonFiniteLossError
from . import _control, _demo, _fit, _identify, _record, _validate
from ._common import INTERRUPTED, CommandError

_COMMANDS = (_demo, _record, _validate, _identify, _control, _fit)

# Failures of the input, the environment, a solver that reports non-convergence or a fit that diverged:
# one line, status 2. Anything else is a bug and keeps its traceback.
_EXPECTED = (
    CommandError,
    ValueError,
    OSError,
    ImportError,
    CheckpointError,
    NonFiniteLossError,
    eqx.EquinoxRuntimeError,
    MemoryError,
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every command."""
    parser = argparse.ArgumentParser(
        prog="cldyn",
        description="Constrained Lagrangian dynamics in keypoint coordinates (KeyCLD).",
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    subparsers = parser.add_subparsers(dest="command", metavar="<command>")
    for command in _COMMANDS:
        command.register(subparsers)
    return parser


def main(argv: list[str] | None = None, *, parser: argparse.ArgumentParser | None = None) -> int:
    """Run the command line on `argv` (default `sys.argv[1:]`); returns the exit status.

    Bad options and expected failures print `cldyn <command>: error: <message>` and return 2; Ctrl-C
    returns 130. Never raises `SystemExit`, so it can be called in-process. `parser` (default
    `build_parser()`) lets another program built of such commands (`keyvision`) share this error path;
    messages start with its `prog`.
    """
    parser = build_parser() if parser is None else parser
    program = parser.prog
    try:
        args, unknown = parser.parse_known_args(argv)
        if unknown:  # named by the command they were given to, as every other argument error
            getattr(args, "command_parser", parser).error(f"unrecognized arguments: {' '.join(unknown)}")
    except SystemExit as exit:  # argparse's own errors (status 2) and --help (status 0)
        return exit.code if isinstance(exit.code, int) else (0 if exit.code is None else 2)
    if args.version:
        from .. import __version__

        print(__version__)
        return 0
    if args.command is None:
        parser.print_help()
        return 0
    args.argv = list(sys.argv[1:] if argv is None else argv)  # for the resume command fit prints
    try:
        return int(args.run(args) or 0)
    except KeyboardInterrupt:
        print(f"{program} {args.command}: interrupted", file=sys.stderr)
        return INTERRUPTED
    except _EXPECTED as error:
        what = f"out of memory ({error})" if isinstance(error, MemoryError) else str(error)
        print(f"{program} {args.command}: error: {what}", file=sys.stderr)
        return 2
