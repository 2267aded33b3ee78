"""Every public name has a docstring and appears in docs/; the docs pages exist; the package layout
follows the abstract-or-final rule of STYLE.md."""

import importlib
import inspect
import pathlib
import re
import subprocess
import sys

import equinox as eqx

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "docs"))
import make_api  # noqa: E402


def test_every_public_name_has_a_docstring():
    assert make_api.missing_docstrings() == []


def test_api_reference_is_up_to_date():
    assert (ROOT / "docs" / "api.md").read_text() == make_api.render(), "run `python docs/make_api.py`"


def test_pages_linked_from_the_index_exist():
    index = (ROOT / "docs" / "index.md").read_text()
    for page in re.findall(r"\(([a-z_]+\.md)", index):
        assert (ROOT / "docs" / page).exists(), page


def test_modules_are_abstract_or_final():
    """STYLE.md rule 4: a concrete Equinox module is never subclassed."""
    import cldyn

    seen = set()

    def walk(cls):
        for sub in cls.__subclasses__():
            if sub.__module__.startswith(("cldyn", "keyvision")) and sub not in seen:
                seen.add(sub)
                walk(sub)

    walk(eqx.Module)
    for cls in seen:
        if inspect.isabstract(cls) or cls.__name__.startswith(("Abstract", "_Abstract")):
            continue
        subclasses = [s for s in cls.__subclasses__() if s.__module__.startswith(("cldyn", "keyvision"))]
        assert not subclasses, f"{cls.__name__} is concrete but subclassed by {subclasses}"
    assert cldyn.ConstrainedLagrangian in seen


def test_cldyn_imports_without_mujoco():
    code = (
        "import sys; sys.modules['mujoco'] = None; sys.modules['dm_control'] = None; "
        "import cldyn; from cldyn._cli import build_parser; build_parser(); print('ok')"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "ok"


def test_readme_starts_with_the_two_commands():
    readme = (ROOT / "README.md").read_text()
    head = readme[: readme.index("\n## ")] if "\n## " in readme else readme
    assert "make demo" in head and "make test" in head


def test_import_time_is_light():
    code = "import cldyn, sys; print(int('mujoco' in sys.modules), int('matplotlib' in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["0", "0"]
    importlib.import_module("cldyn")
