"""The architecture rules of DESIGN.md and STYLE.md that a reader can check by counting.

- no module of cldyn or keyvision is longer than 600 lines (one concept per module);
- no function takes more than 8 positional parameters (the rest are keyword-only);
- only the command line (`cldyn/_cli/`) switches JAX to 64-bit mode;
- `import cldyn` imports none of the optional extras (MuJoCo, matplotlib, tqdm).
- no committed result or model file names a path on the machine that wrote it (a clone elsewhere
  must read the same).
"""

import ast
import pathlib
import re
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGES = ("cldyn", "keyvision")
MAX_LINES = 600
MAX_POSITIONAL = 8


def _sources():
    return sorted(p for package in PACKAGES for p in (ROOT / package).rglob("*.py"))


def test_the_walk_sees_every_area():
    names = {p.relative_to(ROOT).as_posix() for p in _sources()}
    for expected in ("cldyn/_integrate.py", "cldyn/_cli/__init__.py", "cldyn/mujoco/_bridge.py"):
        assert expected in names


@pytest.mark.parametrize("path", _sources(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_modules_are_short(path):
    lines = len(path.read_text().splitlines())
    assert lines <= MAX_LINES, f"{path.relative_to(ROOT)} has {lines} lines (at most {MAX_LINES})"


def test_functions_take_few_positional_parameters():
    offenders = []
    for path in _sources():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                arguments = node.args.posonlyargs + node.args.args
                positional = [a.arg for a in arguments if a.arg not in ("self", "cls")]
                if len(positional) > MAX_POSITIONAL:
                    where = f"{path.relative_to(ROOT)}:{node.lineno}"
                    offenders.append(f"{where} {node.name} ({len(positional)})")
    assert not offenders, "functions with more than 8 positional parameters: " + ", ".join(offenders)


def test_only_the_command_line_turns_on_64_bit_mode():
    switches = [
        p.relative_to(ROOT).as_posix()
        for p in _sources()
        if "jax_enable_x64" in p.read_text() and "_cli" not in p.relative_to(ROOT).parts
    ]
    assert not switches, f"64-bit mode switched outside cldyn/_cli/: {switches}"


def test_importing_cldyn_imports_no_optional_extra():
    code = (
        "import sys, cldyn\n"
        "print(sorted(m for m in ('mujoco', 'matplotlib', 'tqdm', 'dm_control') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "[]", out.stdout


# a path that only the machine that wrote a result has: a home, a scratch or a checkout directory
_MACHINE_PATH = re.compile(r'"(/(?:work|root|home|tmp|Users)/[^"]*)"')


def test_results_name_no_path_of_the_machine_that_wrote_them():
    files = [
        *(ROOT / "benchmarks" / "results").rglob("*.json"),
        *(ROOT / "keyvision" / "demo").rglob("*.json"),
    ]
    assert len(files) > 20  # the walk sees the results
    found = {
        str(path.relative_to(ROOT)): _MACHINE_PATH.findall(path.read_text()) for path in sorted(files)
    }
    assert {name: paths for name, paths in found.items() if paths} == {}
