"""A pytest plugin for `benchmarks/suite_profile.py`: JAX's trace, lowering and compile events of
every test and the memory maps the process holds after it (Linux), written as one JSON line per test
to the file named by `$SUITE_PROFILE_OUT`."""

import collections
import json
import os
import time

import jax
import pytest

_EVENTS = {
    "/jax/core/compile/backend_compile_duration": "compile",
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
}
_seen: list[tuple[str, str, float]] = []


def _listen(event: str, duration: float, **kwargs) -> None:
    kind = _EVENTS.get(event)
    if kind is not None:
        _seen.append((kind, str(kwargs.get("fun_name", "")), duration))


jax.monitoring.register_event_duration_secs_listener(_listen)


def _memory_maps() -> int | None:
    try:
        with open("/proc/self/maps", "rb") as maps:
            return sum(1 for _ in maps)
    except OSError:
        return None


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    _seen.clear()
    started = time.perf_counter()
    yield
    seconds = time.perf_counter() - started
    totals, counts = collections.Counter(), collections.Counter()
    compiled = collections.defaultdict(lambda: [0.0, 0])  # name -> [seconds, compilations]
    for kind, name, duration in _seen:
        totals[kind] += duration
        counts[kind] += 1
        if kind == "compile":
            compiled[name][0] += duration
            compiled[name][1] += 1
    record = {
        "test": item.nodeid,
        "seconds": seconds,
        **{f"{kind}_s": totals[kind] for kind in ("compile", "trace", "lower")},
        "compilations": counts["compile"],
        "compiled": dict(sorted(compiled.items(), key=lambda kv: -kv[1][0])),
        "maps": _memory_maps(),  # each compiled program JAX keeps holds three (tests/conftest.py)
    }
    with open(os.environ["SUITE_PROFILE_OUT"], "a") as out:
        out.write(json.dumps(record) + "\n")
