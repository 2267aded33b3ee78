"""`main(argv)`: parse, run one command; cldyn's `main` turns expected failures into one error line.

Each command is a module with `register(subparsers)` and `run(args) -> int`, as in `cldyn._cli`. The
modules import JAX, MuJoCo and the networks only inside `run`, so `keyvision --help` is fast.
"""

import argparse

from cldyn._cli._main import main as _cldyn_main

from . import _control, _demo, _distil, _evaluate, _identify, _render, _train

_COMMANDS = (_render, _train, _distil, _evaluate, _control, _identify, _demo)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every command."""
    parser = argparse.ArgumentParser(
        prog="keyvision",
        description="Learn constrained Lagrangian dynamics from images (KeyCLD).",
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    subparsers = parser.add_subparsers(dest="command", metavar="<command>")
    for command in _COMMANDS:
        command.register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line on `argv` (default `sys.argv[1:]`); returns the exit status.

    Bad options and expected failures print `keyvision <command>: error: <message>` and return 2;
    Ctrl-C returns 130. Never raises `SystemExit`, so it can be called in-process.
    """
    return _cldyn_main(argv, parser=build_parser())
