"""The documentation: every public name has a docstring and an entry in the API reference, the site
builds in mkdocs' strict mode, and the packages import light."""

import ast
import importlib
import importlib.util
import inspect
import os
import pathlib
import re
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PACKAGES = ("cldyn", "cldyn.systems", "cldyn.mujoco", "keyvision")
# A docs build takes about 10 s alone; allow for a loaded machine.
BUILD_TIMEOUT_S = 300
DOCS_PACKAGES = ("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers.python")
# An entry of the API reference: `::: package.Name` on its own line.
ENTRY = re.compile(r"^::: ([A-Za-z_][\w.]*)\s*$", re.MULTILINE)


def _init_path(package: str) -> pathlib.Path:
    return ROOT.joinpath(*package.split("."), "__init__.py")


def _static_names(package: str) -> list[str]:
    """The public names an `__init__.py` defines or re-exports, read without importing it."""
    names = []
    for node in ast.parse(_init_path(package).read_text()).body:
        if isinstance(node, ast.ImportFrom) and node.level > 0:
            names += [alias.asname or alias.name for alias in node.names]
        elif isinstance(node, ast.FunctionDef | ast.ClassDef):
            names.append(node.name)
        elif isinstance(node, ast.Assign):
            names += [t.id for t in node.targets if isinstance(t, ast.Name)]
    # a submodule re-exported as a name (`from . import systems as systems`) is a package of its own
    return sorted(n for n in names if not n.startswith("_") and not _is_subpackage(package, n))


def _is_subpackage(package: str, name: str) -> bool:
    return _init_path(f"{package}.{name}").exists()


def _import(package: str):
    """The package, or None when it needs an optional dependency that is not installed."""
    try:
        return importlib.import_module(package)
    except ImportError as error:
        if error.name is not None and error.name.split(".")[0] in ("mujoco", "dm_control"):
            return None
        raise


def public_names(package: str) -> list[str]:
    """What a package exports: no underscore, no submodules."""
    module = _import(package)
    if module is None:
        return _static_names(package)
    return sorted(
        name
        for name, value in vars(module).items()
        if not name.startswith("_") and not inspect.ismodule(value) and name != "annotations"
    )


def api_entries() -> set[str]:
    return {m for page in (DOCS / "api").glob("*.md") for m in ENTRY.findall(page.read_text())}


def _has_docstring(name: str, value) -> bool:
    doc = value.__doc__ if inspect.isclass(value) else inspect.getdoc(value)
    if not doc or not doc.strip():
        return False
    # a dataclass (every Equinox module) without a docstring gets `Name(field: type, ...)`
    return not (inspect.isclass(value) and re.fullmatch(rf"{re.escape(name)}\(.*\)", doc, re.DOTALL))


@pytest.mark.parametrize("package", PACKAGES)
def test_every_public_name_has_a_docstring(package):
    module = _import(package)
    if module is None:
        pytest.skip(f"{package} needs the mujoco extra")
    missing = [
        f"{package}.{name}"
        for name in public_names(package)
        if (inspect.isclass(getattr(module, name)) or callable(getattr(module, name)))
        and not _has_docstring(name, getattr(module, name))
    ]
    assert missing == [], f"public names without a docstring: {missing}"


@pytest.mark.parametrize("package", PACKAGES)
def test_every_public_name_is_in_the_api_reference(package):
    entries = api_entries()
    missing = [f"{package}.{n}" for n in public_names(package) if f"{package}.{n}" not in entries]
    assert missing == [], f"add `::: NAME` entries to a page of docs/api/ for {missing}"


def test_api_reference_names_only_public_names():
    public = {f"{p}.{n}" for p in PACKAGES for n in public_names(p)} | set(PACKAGES)
    stale = sorted(api_entries() - public)
    assert stale == [], f"docs/api/ documents names that are not public: {stale}"


def test_every_page_is_in_the_nav_and_every_link_resolves():
    config = (ROOT / "mkdocs.yml").read_text()
    nav_block = re.search(r"^nav:\n((?:[ #].*\n|\n)*)", config, re.MULTILINE).group(1)
    pages = {str(p.relative_to(DOCS)) for p in DOCS.rglob("*.md")}
    nav = set(re.findall(r"([\w/]+\.md)", nav_block))
    assert pages == nav, f"pages not in the nav: {pages - nav}; nav entries without a page: {nav - pages}"
    for page in DOCS.rglob("*.md"):
        for target in re.findall(r"\]\(([\w/.]+\.md)(?:#[\w-]*)?\)", page.read_text()):
            assert (page.parent / target).resolve().exists(), f"{page.name} links to missing {target}"


def test_docs_build_in_strict_mode(tmp_path):
    for name in DOCS_PACKAGES:
        if importlib.util.find_spec(name) is None:
            pytest.skip(f"{name} is not installed (pip install cldyn[docs])")
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    out = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env=env,
        timeout=BUILD_TIMEOUT_S,
    )
    assert out.returncode == 0, out.stderr[-4000:]
    page = (tmp_path / "site" / "api" / "model" / "index.html").read_text()
    # docstrings are rendered (not just headings), and their $...$ math goes to MathJax
    assert "A mechanical system in keypoint coordinates" in page
    assert 'class="arithmatex"' in page


def test_cldyn_and_its_command_line_work_without_mujoco():
    code = (
        "import runpy, sys; sys.modules['mujoco'] = None; sys.modules['dm_control'] = None; "
        "import cldyn, cldyn.systems; sys.argv = ['cldyn', '--help']; "
        "runpy.run_module('cldyn', run_name='__main__')"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-4000:]
    assert "usage" in out.stdout


def test_readme_starts_with_the_two_commands():
    readme = (ROOT / "README.md").read_text()
    head = readme[: readme.index("\n## ")] if "\n## " in readme else readme
    assert "make demo" in head and "make test" in head


def test_import_time_is_light():
    heavy = ("mujoco", "dm_control", "matplotlib", "tqdm")
    code = f"import cldyn, sys; print(*[int(m in sys.modules) for m in {heavy!r}])"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["0"] * len(heavy), dict(zip(heavy, out.stdout.split()))


# A signature written out in the prose pages, `name(a, b, *, c=1)`: a bare `*` tells it from a call.
SIGNATURE = re.compile(r"((?:cldyn\.mujoco\.|cldyn\.|keyvision\.)?[A-Za-z_]\w*)\(")
SIGNATURE_PACKAGES = ("cldyn", "cldyn.mujoco", "keyvision")  # where a name without a package is looked up


def _written_signatures(text: str):
    """`(name, parameters, line)` of every signature written out in a page. Table rows are left out:
    they abbreviate (`keycld_model(k, l, constraint, *, key)`, the paper's symbols)."""
    for match in SIGNATURE.finditer(text):
        start = text.rfind("\n", 0, match.start()) + 1
        if text[start : match.start()].lstrip().startswith("|"):
            continue
        end, depth = match.end(), 1
        while end < len(text) and depth:
            depth += {"(": 1, ")": -1}.get(text[end], 0)
            end += 1
        parameters = " ".join(text[match.end() : end - 1].split())
        if re.search(r"(^|,)\s*\*\s*(,|$)", parameters):
            yield match.group(1), parameters, text.count("\n", 0, match.start()) + 1


def _resolve(name: str):
    packages = [name.rsplit(".", 1)[0]] if "." in name else SIGNATURE_PACKAGES
    for package in packages:
        module = _import(package)
        value = getattr(module, name.rsplit(".", 1)[-1], None) if module is not None else None
        if callable(value):
            return value
    return None


def _same_default(written, actual) -> bool:
    try:
        same = written == actual
        return bool(same) if isinstance(same, bool) else False
    except Exception:
        return False


def test_signatures_written_in_the_pages_match_the_code():
    import diffrax
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import numpy as np

    import cldyn
    import keyvision

    if _import("cldyn.mujoco") is None:
        pytest.skip("cldyn.mujoco needs the mujoco extra")
    # a default is written as code: `cldyn.Runs(32)`, or a cldyn name alone, `solver=RK4()`
    namespace = {name: getattr(cldyn, name) for name in public_names("cldyn")}
    namespace.update(cldyn=cldyn, keyvision=keyvision, jax=jax, jnp=jnp, np=np, diffrax=diffrax, eqx=eqx)
    problems, found = [], 0
    for page in sorted(DOCS.rglob("*.md")) + [ROOT / "README.md"]:
        for name, parameters, line in _written_signatures(page.read_text()):
            where, found = f"{page.relative_to(ROOT)}:{line} {name}", found + 1
            value = _resolve(name)
            if value is None:
                problems.append(f"{where}: no public callable of that name")
                continue
            written = ast.parse(f"def f({parameters}): pass").body[0].args
            actual = [p for p in inspect.signature(value).parameters.values() if p.name != "self"]
            positional = written.posonlyargs + written.args
            names = [a.arg for a in positional] + ["*"] + [a.arg for a in written.kwonlyargs]
            keyword = (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.VAR_KEYWORD)
            real = [p.name for p in actual if p.kind not in keyword] + ["*"]
            real += [p.name for p in actual if p.kind in keyword]
            if names != real:
                problems.append(f"{where}: written ({', '.join(names)}), the code has ({', '.join(real)})")
                continue
            defaults = dict(zip([a.arg for a in positional][len(positional) - len(written.defaults) :],
                                written.defaults))
            keyword_defaults = zip(written.kwonlyargs, written.kw_defaults)
            defaults.update({a.arg: d for a, d in keyword_defaults if d is not None})
            for parameter in actual:
                text = ast.unparse(defaults[parameter.name]) if parameter.name in defaults else None
                if (text is None) != (parameter.default is inspect.Parameter.empty):
                    problems.append(f"{where}: `{parameter.name}` written with default {text or 'none'}, "
                                    f"the code's: {'none' if text else repr(parameter.default)}")
                elif text is not None and not _same_default(eval(text, namespace), parameter.default):
                    problems.append(f"{where}: `{parameter.name}={text}`, the code's default is "
                                    f"{parameter.default!r}")
    assert found >= 8, f"only {found} written signatures found: has the pattern stopped matching?"
    assert problems == [], "\n".join(problems)
