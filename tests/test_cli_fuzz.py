"""Fuzzing the command line in-process: every invalid option value hypothesis can think of gives status 2
and one `cldyn <command>: error: ...` line, never a traceback, and creates nothing, before any work.

The invalid values are drawn from what each option's argparse type accepts (read off the parser, so a new
option is fuzzed without touching this file): non-numbers, NaN and infinities, numbers out of range,
non-integers for counts, unknown choices, missing values, and combinations of valid values that the
commands refuse (LOW >= HIGH, a run shorter than a sample, --force without --resume). Each call is
milliseconds, since nothing is simulated.

`CLDYN_FUZZ_EXAMPLES=1000 pytest -s tests/test_cli_fuzz.py` runs 1,000 invocations per command and prints
the counts (the suite runs a few dozen).
"""

import argparse
import contextlib
import functools
import io
import os
import pathlib
import tempfile

import numpy as np
import pytest

pytest.importorskip("hypothesis")  # the dev extra

from hypothesis import HealthCheck, given, settings, strategies as st  # noqa: E402

import cldyn  # noqa: E402
from cldyn._cli import build_parser, main  # noqa: E402

EXAMPLES = int(os.environ.get("CLDYN_FUZZ_EXAMPLES", "30"))

# command -> its required arguments; "{out}" is a fresh directory per invocation that must stay empty
REQUIRED = {
    "demo": ["--out", "{out}"],
    "record": ["--mjcf", "keycld/pendulum", "--out", "{out}/x.npz"],
    "validate": ["--mjcf", "keycld/pendulum", "--out", "{out}"],
    "identify": ["--data", "{data}", "--model", "acrobot", "--out", "{out}"],
    "control": ["--mjcf", "keycld/pendulum", "--out", "{out}"],
    "fit": ["--scene", "pendulum", "--out", "{out}"],
}
COUNTS: dict[str, int] = {}


@functools.cache
def _subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    (action,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(action.choices)


def _options(command: str) -> list[argparse.Action]:
    parser = _subparsers()[command]
    return [a for a in parser._actions if a.option_strings and a.option_strings[0] != "-h"]


def _refused(parse, text: str) -> bool:
    try:
        parse(text)
    except (argparse.ArgumentTypeError, ValueError):
        return True
    return False


_NUMBER_TEXT = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-(10**30), 10**30).map(str),
    st.sampled_from(["nan", "NaN", "-nan", "inf", "-inf", "Infinity", "1e999", "-1e999", "0", "-0", "0.0"]),
    st.sampled_from(["-1", "-0.5", "1.5", "0.5", "1", "2e-3", "1e3", "1_0", "0x10", "", " ", "1,5", "½"]),
    st.text(max_size=12),
)


def _invalid_value(action: argparse.Action):
    """A strategy of values the option's type refuses, or of unknown choices."""
    parse = action.type
    if getattr(parse, "accepts", None) is not None:
        return _NUMBER_TEXT.filter(lambda text: _refused(parse, text))
    if action.choices is not None:
        return st.text(max_size=12).filter(lambda text: text not in action.choices)
    return None


def _base(command: str, out: pathlib.Path, data: pathlib.Path) -> list[str]:
    return [a.format(out=out, data=data) for a in REQUIRED[command]]


@st.composite
def _mutation(draw, command: str):
    """Arguments to add to the required ones that make the invocation invalid."""
    options = _options(command)
    typed = [a for a in options if _invalid_value(a) is not None]
    kind = draw(st.sampled_from(["value", "value", "value", "missing", "combination"]))
    if kind == "missing":  # an option that takes a value, given none
        action = draw(st.sampled_from([a for a in options if a.nargs not in (0, "*", "?")]))
        return [action.option_strings[0]]
    if kind == "combination":
        combination = _combination(command)
        if combination is not None:
            return draw(combination)
    action = draw(st.sampled_from(typed))
    bad = draw(_invalid_value(action))
    option = action.option_strings[0]
    if action.nargs is None:  # "--x=-1" is read as a value, "--x -y" as a missing value and an option
        return draw(st.sampled_from([[f"{option}={bad}"], [option, bad]]))
    count = 2 if action.nargs == 2 else draw(st.integers(1, 3))
    values = [bad] + ["1"] * (count - 1)
    draw(st.randoms()).shuffle(values)
    return [option] + values


def _combination(command: str):
    """Valid values in combinations the command refuses before any work."""
    finite = st.floats(-1e6, 1e6, allow_nan=False)
    if command == "record":
        return st.tuples(finite, finite).map(
            lambda pair: ["--control-range", repr(max(pair)), repr(min(pair))]
        ) | st.text(max_size=20).filter(_not_a_scene).map(lambda text: ["--mjcf", text])
    if command == "validate":
        return st.tuples(st.floats(1e-6, 1.0), st.floats(0.01, 0.99)).map(
            lambda p: ["--dt", repr(p[0]), "--duration", repr(p[0] * p[1])]
        )
    if command == "fit":
        return st.sampled_from(
            [
                ["--force"],
                ["--resume", "--overwrite"],
                ["--runs", "50"],
                ["--runs", "60", "--batch-size", "11"],
            ]
        )
    return None


def _not_a_scene(text: str) -> bool:
    """Random text that names neither a scene, a suite domain nor an existing path."""
    if text.strip().startswith("<") or text.startswith("keycld/") or text.startswith("-"):
        return False
    return not (text.isidentifier() and text.islower()) and not os.path.exists(text)


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> pathlib.Path:
    x = np.zeros((4, 10, 2))
    return cldyn.Sequences(x, np.zeros((4, 10, 1)), 0.01).save(tmp_path_factory.mktemp("fuzz") / "d.npz")


def _check(command: str, mutation: list[str], data: pathlib.Path) -> None:
    with tempfile.TemporaryDirectory() as root:
        out = pathlib.Path(root) / "out"
        argv = [command] + _base(command, out, data) + mutation
        stdout, stderr = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            status = main(argv)
        COUNTS[command] = COUNTS.get(command, 0) + 1
        err = stderr.getvalue()
        assert "Traceback" not in err, (argv, err)
        assert status == 2, (argv, status, err)
        assert f"cldyn {command}: error: " in err, (argv, err)
        assert not any(pathlib.Path(root).iterdir()), (argv, list(pathlib.Path(root).rglob("*")))


@pytest.mark.parametrize("command", sorted(REQUIRED))
def test_invalid_options_are_one_error_line(command, data):
    @settings(
        max_examples=EXAMPLES,
        deadline=None,
        database=None,
        suppress_health_check=[HealthCheck.filter_too_much, HealthCheck.too_slow],
    )
    @given(mutation=_mutation(command))
    def fuzz(mutation):
        _check(command, mutation, data)

    COUNTS[command] = 0
    fuzz()
    print(f"fuzz {command}: {COUNTS[command]} invalid invocations, no traceback")
