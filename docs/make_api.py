"""Generate docs/api.md from the docstrings of every public name.

    python docs/make_api.py          # rewrite docs/api.md
    python docs/make_api.py --check  # exit 1 if docs/api.md is out of date

The test suite runs the check, so every public name has a docstring and appears in the docs.
"""

import importlib
import inspect
import pathlib
import sys

PACKAGES = ("cldyn", "cldyn.systems", "cldyn.mujoco", "keyvision")
OUT = pathlib.Path(__file__).resolve().parent / "api.md"


def public_names(module) -> list[str]:
    """The names a package exports: no underscore, defined in the package, not submodules."""
    names = []
    for name, value in vars(module).items():
        if name.startswith("_") or inspect.ismodule(value):
            continue
        origin = getattr(value, "__module__", None) or ""
        if isinstance(value, tuple) or origin.split(".")[0] == module.__name__.split(".")[0]:
            names.append(name)
    return sorted(names, key=lambda n: (not inspect.isclass(getattr(module, n)), n.lower()))


def _signature(value) -> str:
    try:
        signature = inspect.signature(value)
    except (TypeError, ValueError):
        return ""
    text = str(signature)
    return text if len(text) < 400 else "(...)"


def _entry(package: str, name: str, value) -> list[str]:
    kind = "class" if inspect.isclass(value) else "function" if callable(value) else "constant"
    lines = [f"### `{package}.{name}`", ""]
    if kind == "constant":
        lines += [f"`{name} = {value!r}`", ""]
        return lines
    lines += [f"```python\n{name}{_signature(value)}\n```", ""]
    doc = inspect.getdoc(value)
    lines += [doc or "", ""]
    if inspect.isclass(value):
        root = package.split(".")[0]
        methods = []
        for member in dir(value):
            owner = next((c for c in value.__mro__ if member in vars(c)), None)
            if member.startswith("_") or owner is None or not owner.__module__.startswith(root):
                continue
            attribute = vars(owner)[member]
            if isinstance(attribute, property | classmethod | staticmethod) or inspect.isfunction(attribute):
                target = (
                    attribute.__func__ if isinstance(attribute, classmethod | staticmethod) else attribute
                )
                doc = inspect.getdoc(target) or ""
                methods.append(f"- `{member}`: {doc.splitlines()[0] if doc else ''}")
        if methods:
            lines += methods + [""]
    return lines


def render() -> str:
    lines = [
        "# API reference",
        "",
        "Generated from the docstrings by `python docs/make_api.py`; every public name of the packages "
        "below appears here.",
        "",
    ]
    for package in PACKAGES:
        try:
            module = importlib.import_module(package)
        except ImportError:
            continue
        lines += [f"## `{package}`", ""]
        doc = inspect.getdoc(module)
        if doc:
            lines += [doc, ""]
        for name in public_names(module):
            lines += _entry(package, name, getattr(module, name))
    return "\n".join(lines).rstrip() + "\n"


def missing_docstrings() -> list[str]:
    """Public names without a docstring."""
    missing = []
    for package in PACKAGES:
        try:
            module = importlib.import_module(package)
        except ImportError:
            continue
        for name in public_names(module):
            value = getattr(module, name)
            if callable(value) and not inspect.getdoc(value):
                missing.append(f"{package}.{name}")
    return missing


if __name__ == "__main__":
    text = render()
    if "--check" in sys.argv:
        if not OUT.exists() or OUT.read_text() != text:
            print("docs/api.md is out of date: run `python docs/make_api.py`", file=sys.stderr)
            sys.exit(1)
        sys.exit(0)
    OUT.write_text(text)
    print(f"wrote {OUT}")
