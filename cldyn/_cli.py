"""The `cldyn` command line: `cldyn <command> [options]` (also `python -m cldyn`).

Each command lives next to the code it drives and registers itself here through a `register(subparsers)`
function; modules are imported only when the command line is parsed, so `import cldyn` stays light and
commands that need MuJoCo are listed even when it is not installed.
"""

import argparse
import importlib
import sys

# (module, description) for every command group; each module defines `register(subparsers)`.
_COMMAND_MODULES = (
    "cldyn._demo",
    "cldyn.mujoco._cli",
    "cldyn.mujoco._identify",
    "cldyn.mujoco._control",
    "cldyn._learn_cli",
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every available command."""
    parser = argparse.ArgumentParser(
        prog="cldyn",
        description="Constrained Lagrangian dynamics in keypoint coordinates (KeyCLD).",
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    subparsers = parser.add_subparsers(dest="command", metavar="<command>")
    for name in _COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ImportError as error:
            if error.name is not None and error.name.split(".")[0] in ("mujoco", "dm_control"):
                continue
            if error.name == name:
                continue
            raise
        module.register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.version:
        from . import __version__

        print(__version__)
        return 0
    if args.command is None:
        parser.print_help()
        return 0
    try:
        return int(args.run(args) or 0)
    except (ValueError, FileNotFoundError, RuntimeError) as error:
        print(f"cldyn {args.command}: error: {error}", file=sys.stderr)
        return 2
