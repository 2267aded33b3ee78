import os

os.environ.setdefault("MUJOCO_GL", "egl")

import jax
import pytest

# Physics tests compare against independent derivations to 1e-9 and better: float64 throughout.
# Tests that exercise float32 training cast explicitly.
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
# A float32 array meeting a float64 one (or an integer array meeting a float) silently changes
# precision; in the tests that is a bug, so it raises. Python scalars stay weakly typed.
jax.config.update("jax_numpy_dtype_promotion", "strict")

# No persistent compilation cache: writing an entry serialises the compiled executable, and that
# crashed a pytest-xdist worker twice in five full runs on 2026-11-26 (a segmentation fault in
# `LoadedExecutable.serialize` under `compilation_cache.put_executable_and_time`, and an abort), after
# which the run hung waiting for the lost worker. The cache had saved about a sixth of the wall time.

# Test modules whose code under test still mixes dtypes implicitly: they run with JAX's standard
# promotion until the code is fixed. Name -> the first error seen under strict promotion.
STANDARD_PROMOTION: dict[str, str] = {}


@pytest.fixture(autouse=True)
def _dtype_promotion(request):
    module = request.node.path.name if request.node.path is not None else ""
    if module in STANDARD_PROMOTION:
        with jax.numpy_dtype_promotion("standard"):
            yield
    else:
        yield


_STEP_FUNCTIONS = ("jit(_compiled_chunk)", "jit(_host_step)")


@pytest.fixture
def step_compilations():
    """The names of the optimiser-step functions XLA compiles while the test runs (JAX's monitoring
    event of a backend compilation)."""
    names: list[str] = []

    def listen(event, duration, **kwargs):
        del duration
        name = str(kwargs.get("fun_name", ""))
        if event == "/jax/core/compile/backend_compile_duration" and name in _STEP_FUNCTIONS:
            names.append(name)

    jax.monitoring.register_event_duration_secs_listener(listen)
    yield names
    jax.monitoring.unregister_event_duration_listener(listen)


def pytest_collection_modifyitems(config, items):
    """Modules with slow tests first, a module's tests together (`pytest -n 2` without `make test`'s
    `--dist loadfile` then shares the long tests between the workers, and the short ones even out
    the end of the run). `make test` hands whole modules to the workers, most tests first."""
    slow = {item.module.__name__ for item in items if item.get_closest_marker("slow") is not None}
    items.sort(key=lambda item: item.module.__name__ not in slow)
