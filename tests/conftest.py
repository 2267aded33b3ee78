import gc
import os
import pathlib
import subprocess
import sys

os.environ.setdefault("MUJOCO_GL", "egl")

# XLA's CPU code generator without its newer fusion emitters: the suite spends most of its time
# compiling, and the older emitter compiles the same programs about a third faster (`make test` in a
# fresh clone on 2 cores: 864-926 s in five runs with XLA's defaults, 570 s with this, jaxlib 0.10.2,
# 2026-11-27). Results agree to rounding: a float64 acrobot rollout of 500 steps to 2.2e-15 m, a
# float32 estimator and renderer bit for bit. Set XLA_FLAGS with `--xla_cpu_use_fusion_emitters=true`
# to run the suite with XLA's defaults. A flag this XLA does not know aborts the process, so it is
# tried in a subprocess first; the xdist workers and the tests' own subprocesses inherit it.
_FAST_COMPILE = "--xla_cpu_use_fusion_emitters=false"


def _compile_faster() -> None:
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_use_fusion_emitters" in flags:
        return
    flags = f"{flags} {_FAST_COMPILE}".strip()
    try:
        probe = subprocess.run(
            [sys.executable, "-c", "import jax; jax.numpy.zeros(1).block_until_ready()"],
            env=dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu"),
            capture_output=True,
            timeout=120,
        )
    except (OSError, subprocess.TimeoutExpired):
        return  # XLA's defaults: slower, the same tests
    if probe.returncode == 0:
        os.environ["XLA_FLAGS"] = flags


_compile_faster()

import jax  # noqa: E402
import pytest  # noqa: E402

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


def _memory_maps() -> tuple[int, int] | None:
    """`(maps, limit)`: the memory maps this process holds and the kernel's limit on them (Linux only)."""
    try:
        with open("/proc/self/maps", "rb") as maps:
            count = sum(1 for _ in maps)
        return count, int(pathlib.Path("/proc/sys/vm/max_map_count").read_text())
    except (OSError, ValueError):
        return None


@pytest.fixture(autouse=True, scope="module")
def _bounded_executables():
    """JAX's caches cleared after a test module once the process holds half of Linux's memory maps.

    Each compiled XLA CPU program holds three memory maps (its code, constants and data) for as long
    as JAX caches it, and an `eqx.filter_jit` program stays cached after the function it compiled is
    gone (200 such closures, dropped: 599 maps more, until `jax.clear_caches()`). Linux allows a
    process `vm.max_map_count` maps, 65530 by default. The whole suite in one process (`pytest -p
    no:xdist`, `benchmarks/suite_profile.py`) reached it in 17 minutes (65024 maps at the last sample)
    and XLA died of a segmentation fault compiling the next program, in the same test of
    `test_keyvision_control.py` in three runs (2026-12-04); with this fixture the same run passes (667
    tests in 1136 s, the caches cleared twice, the maps never above 35000). Clearing costs a
    recompilation of what a later module shares with an earlier one, so it waits until it is needed."""
    yield
    held = _memory_maps()
    if held is not None and held[0] > held[1] // 2:
        jax.clear_caches()
        gc.collect()


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
