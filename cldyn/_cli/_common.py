"""What every command shares: argument types, the help format, output checks and the float64 switch.

Argument types turn a bad number into argparse's own error (`cldyn <command>: error: argument --x: ...`,
exit status 2) before any work starts; the checks are `cldyn._misc`'s, so the library and the command
line refuse the same values with the same words.
"""

import argparse
import json
import math
import os
import pathlib
import tempfile
from collections.abc import Callable

from .._misc import check_fraction, check_positive

INTERRUPTED = 130  # the exit status of a command stopped by Ctrl-C (128 + SIGINT)


def differences(old, new, prefix: str = "") -> list[str]:
    """`name old -> new` for every setting that differs between two records of a command's options
    (nested names joined by dots; a record's `previous` settings left out), so that a refused
    `--resume` names what to give."""
    if isinstance(old, dict) and isinstance(new, dict):
        names = [n for n in {**old, **new} if n != "previous"]
        return [d for n in names for d in differences(old.get(n), new.get(n), f"{prefix}{n}.")]
    return [] if old == new else [f"{prefix.rstrip('.')} {json.dumps(old)} -> {json.dumps(new)}"]


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
        # flags (nargs 0) say what they do: "--no-progress (default: True)" would read backwards
        shown = default is not None and action.nargs != 0 and default != [] and default != ()
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
    # what the type accepts, for the fuzz test that generates values it must refuse
    parse.accepts = ("integer" if integer else "number", ">= 0" if allow_zero else "> 0")
    return parse


def fraction(text: str) -> float:
    """An argparse type: a number strictly between 0 and 1."""
    try:
        return check_fraction("value", text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(_strip(str(error))) from None


fraction.accepts = ("number", "in (0, 1)")


def finite(text: str) -> float:
    """An argparse type: any finite number."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


finite.accepts = ("number", "finite")


def seed(text: str) -> int:
    """An argparse type: a seed, an integer `>= 0`."""
    return positive(integer=True, allow_zero=True)(text)


seed.accepts = ("integer", ">= 0")


def add_overwrite(parser: argparse.ArgumentParser, what: str) -> None:
    """The `--overwrite` flag: without it, a command refuses to replace results already at `--out`."""
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help=f"replace {what} already at --out (without it the command refuses before any work)",
    )


def refuse_existing(files, *, overwrite: bool, hint: str = "pass --overwrite to replace") -> None:
    """Refuse, before any work, to replace the results `files` of an earlier run unless `overwrite`."""
    existing = [str(f) for f in files if os.path.lexists(f)]
    if existing and not overwrite:
        which = "exists" if len(existing) == 1 else "exist"
        raise CommandError(f"--out: {', '.join(existing)} already {which} (an earlier run's results); {hint}")


def enable_float64() -> None:
    """Switch JAX to float64 for the rest of the process: the one place the library allows it."""
    import jax

    jax.config.update("jax_enable_x64", True)


def _writable_directory(directory: pathlib.Path, label: str) -> None:
    """Check that files can be created in `directory`, or in its nearest existing ancestor if it does
    not exist yet. The check creates a temporary file and removes it at once: permission bits say
    nothing for root, read-only mounts or `/proc`, and a run that fails later must leave no empty
    directories behind."""
    probe = directory
    while not probe.exists() and probe.parent != probe:
        probe = probe.parent
    if not probe.is_dir():
        raise CommandError(f"{label}: {probe} is a file, not a directory")
    try:
        with tempfile.TemporaryFile(dir=probe, prefix=".cldyn-write-check-"):
            pass
    except OSError as error:
        reason = error.strerror or type(error).__name__
        raise CommandError(f"{label}: cannot create files in {probe} ({reason})") from None


def output_directory(
    path: "str | os.PathLike", *, results: tuple[str, ...] = (), overwrite: bool = False
) -> pathlib.Path:
    """Check, before any work, that results can be written into the directory `path` (which the
    command's writers create if needed) and that the files `results` there, an earlier run's, are
    not replaced unless `overwrite`."""
    directory = pathlib.Path(path)
    if directory.exists() and not directory.is_dir():
        raise CommandError(f"--out {directory}: exists and is not a directory")
    _writable_directory(directory, f"--out {directory}")
    refuse_existing([directory / name for name in results], overwrite=overwrite)
    return directory


def output_file(path: "str | os.PathLike", *, suffix: str, overwrite: bool = False) -> pathlib.Path:
    """Check, before any work, that the file `path` (with `suffix` appended if it lacks it, as the
    writer does) can be written and does not exist unless `overwrite`; its directory is created by
    the writer if needed."""
    file = pathlib.Path(path)
    if file.suffix != suffix:
        file = file.with_name(file.name + suffix)
    if file.is_dir():
        raise CommandError(f"--out {file}: is a directory; give a file name")
    _writable_directory(file.parent, f"--out {file}")
    refuse_existing([file], overwrite=overwrite)
    return file


def input_file(path: "str | os.PathLike", option: str) -> pathlib.Path:
    """An existing file, or an error naming the option."""
    file = pathlib.Path(path)
    if not file.is_file():
        raise CommandError(f"{option} {file}: no such file")
    return file
