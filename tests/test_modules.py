"""Every Equinox module of cldyn and keyvision is abstract or final (STYLE.md rule 4).

A concrete module is never subclassed; shared code lives in an abstract base. The walk imports every
submodule (private ones included), so a class anywhere in either package is checked.
"""

import importlib
import inspect
import pkgutil

import equinox as eqx
import pytest

PACKAGES = ("cldyn", "keyvision")
OPTIONAL = ("mujoco", "dm_control", "matplotlib", "imageio", "tqdm")


def _import_everything() -> list[str]:
    """Import every submodule of both packages; return those that need a missing optional extra."""
    skipped = []
    for root in PACKAGES:
        package = importlib.import_module(root)
        for info in pkgutil.walk_packages(package.__path__, prefix=f"{root}."):
            if info.name.endswith(".__main__"):  # runs the command line on import
                continue
            try:
                importlib.import_module(info.name)
            except ImportError as error:
                if error.name is None or error.name.split(".")[0] not in OPTIONAL:
                    raise
                skipped.append(info.name)
    return skipped


def _walk(cls, seen):
    for sub in cls.__subclasses__():
        if sub.__module__.split(".")[0] in PACKAGES and sub not in seen:
            seen.add(sub)
            _walk(sub, seen)
        elif sub not in seen:
            # a class of another library (equinox, lineax, diffrax) may be the parent of ours
            _walk(sub, seen)
    return seen


def _is_abstract(cls) -> bool:
    abstract_vars = getattr(cls, "__abstractvars__", None) or getattr(cls, "__abstractclassvars__", None)
    return (
        inspect.isabstract(cls)
        or bool(abstract_vars)
        or cls.__name__.startswith(("Abstract", "_Abstract"))
    )


@pytest.fixture(scope="module")
def modules():
    _import_everything()
    return {c for c in _walk(eqx.Module, set()) if c.__module__.split(".")[0] in PACKAGES}


def test_the_walk_finds_modules_of_every_area(modules):
    import cldyn

    names = {c.__qualname__ for c in modules}
    for expected in (cldyn.ConstrainedLagrangian, cldyn.Distance, cldyn.PointMasses, cldyn.RK4):
        assert expected in modules
    assert any(c.__module__.startswith("keyvision") for c in modules), names
    assert len(modules) > 40


def test_modules_are_abstract_or_final(modules):
    offenders = []
    for cls in sorted(modules, key=lambda c: (c.__module__, c.__qualname__)):
        if _is_abstract(cls):
            continue
        subclasses = [s.__qualname__ for s in modules if cls in s.__mro__[1:]]
        if subclasses:
            name = f"{cls.__module__}.{cls.__qualname__}"
            offenders.append(f"{name} is concrete but subclassed by {subclasses}")
    assert offenders == [], "\n".join(offenders)


def test_abstract_modules_are_named_so(modules):
    """A class with abstract methods is a base: its name says so (STYLE.md rule 3)."""
    unnamed = [
        f"{c.__module__}.{c.__qualname__}"
        for c in modules
        if inspect.isabstract(c) and not c.__name__.startswith(("Abstract", "_Abstract"))
    ]
    assert unnamed == []
