"""What every command shares: argument types, the help format, output checks and the float64 switch.

Argument types turn a bad number into argparse's own error (`cldyn <command>: error: argument --x: ...`,
exit status 2) before any work starts; the checks are `cldyn._misc`'s, so the library and the command
line refuse the same values with the same words.
"""

import argparse
import os
import pathlib
from collections.abc import Callable

from .._misc import check_fraction, check_positive

INTERRUPTED = 130  # the exit status of a command stopped by Ctrl-C (128 + SIGINT)


class CommandError(Exception):
    """An expected failure of a command: printed as `cldyn <command>: error: <message>`, exit status 2."""


class Formatter(argparse.HelpFormatter):
    """Fills each paragraph of a description on its own and shows each option's default where it has
    one."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        paragraphs = [" ".join(p.split()) for p in text.strip().split("\n\n")]
        return "\n\n".join(super(Formatter, self)._fill_text(p, width, indent) for p in paragraphs)

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        shown = default is not None and default is not False and default != [] and default != ()
        if shown and default is not argparse.SUPPRESS and action.option_strings and "default" not in text:
            text += " (default: %(default)s)"
        return text


def add_command(subparsers, name: str, *, help: str, description: str) -> argparse.ArgumentParser:
    """A subcommand's parser with the shared help format; it reports its own argument errors."""
    parser = subparsers.add_parser(name, help=help, description=description, formatter_class=Formatter)
    parser.set_defaults(command_parser=parser)
    return parser


def _strip(message: str) -> str:
    # check_positive names the value it checked; argparse already names the option.
    return message.removeprefix("value ")


def positive(*, integer: bool = False, allow_zero: bool = False) -> Callable[[str], float | int]:
    """An argparse type: a finite number `> 0` (`>= 0` with `allow_zero`), an integer where `integer`."""

    def parse(text: str):
        try:
            value = int(text) if integer else float(text)
        except ValueError:
            kind = "an integer" if integer else "a number"
            raise argparse.ArgumentTypeError(f"must be {kind}, got {text!r}") from None
        try:
            return check_positive("value", value, integer=integer, allow_zero=allow_zero)
        except ValueError as error:
            raise argparse.ArgumentTypeError(_strip(str(error))) from None

    parse.__name__ = "integer" if integer else "number"
    return parse


def fraction(text: str) -> float:
    """An argparse type: a number strictly between 0 and 1."""
    try:
        return check_fraction("value", text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(_strip(str(error))) from None


def seed(text: str) -> int:
    """An argparse type: a seed, an integer `>= 0`."""
    return positive(integer=True, allow_zero=True)(text)


def enable_float64() -> None:
    """Switch JAX to float64 for the rest of the process: the one place the library allows it."""
    import jax

    jax.config.update("jax_enable_x64", True)


def _writable_directory(directory: pathlib.Path, label: str) -> None:
    """Check that files can be created in `directory`, or in its nearest existing ancestor if it does
    not exist yet (nothing is created here: a run that fails later leaves no empty directories)."""
    probe = directory
    while not probe.exists() and probe.parent != probe:
        probe = probe.parent
    if not probe.is_dir():
        raise CommandError(f"{label}: {probe} is a file, not a directory")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise CommandError(f"{label}: cannot write in {probe} (permission denied or read-only)")


def output_directory(path: "str | os.PathLike") -> pathlib.Path:
    """Check, before any work, that results can be written into the directory `path` (which the
    command's writers create if needed)."""
    directory = pathlib.Path(path)
    if directory.exists() and not directory.is_dir():
        raise CommandError(f"--out {directory}: exists and is not a directory")
    _writable_directory(directory, f"--out {directory}")
    return directory


def output_file(path: "str | os.PathLike") -> pathlib.Path:
    """Check, before any work, that the file `path` can be written (its directory is created by the
    writer if needed)."""
    file = pathlib.Path(path)
    if file.is_dir():
        raise CommandError(f"--out {file}: is a directory; give a file name")
    _writable_directory(file.parent, f"--out {file}")
    return file


def input_file(path: "str | os.PathLike", option: str) -> pathlib.Path:
    """An existing file, or an error naming the option."""
    file = pathlib.Path(path)
    if not file.is_file():
        raise CommandError(f"{option} {file}: no such file")
    return file
