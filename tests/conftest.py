import os
import tempfile

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

# Compiled programs are shared between the pytest-xdist workers (and later runs) through JAX's
# persistent cache; compilation is most of the suite's time on two cores. Every program, however
# small: the thousands of small ones the tests share cost less to read than to compile (measured on
# five test modules: 16% less wall time than caching only programs that take 0.5 s or more).
jax.config.update("jax_compilation_cache_dir", os.path.join(tempfile.gettempdir(), "cldyn-jax-cache"))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)

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


def pytest_collection_modifyitems(config, items):
    """Modules with slow tests first: the two workers share the long tests, and the short ones even
    out the end of the run instead of one long test keeping a worker busy after the other has
    finished. A module's tests stay together, so its module-scoped fixtures are built once."""
    slow = {item.module.__name__ for item in items if item.get_closest_marker("slow") is not None}
    items.sort(key=lambda item: item.module.__name__ not in slow)
