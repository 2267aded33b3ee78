"""Where the test suite's time goes: per test, module and compiled function, the wall time and JAX's
tracing, lowering and XLA compile time.

The suite is compile-bound on a CPU (2026-11-28, one process on 2 cores: of 881 s of tests, XLA
compiled for 377 s, tracing and lowering took much of the rest), so this is the first thing to look
at when it grows. The tests run in one process (no xdist: the events
of one test are not mixed with another's), through a plugin (`benchmarks/_compile_events.py`) that
listens to JAX's monitoring events. Tracing events nest (an inner jit traced inside an outer one
reports too), so trace times may count some time twice.

Writes benchmarks/results/suite_profile.json (the totals by module and function, and every test of a
second or more) and suite_profile.md (the largest modules, tests and functions); prints the
summary. Pass test paths or pytest options after `--` to profile part of the suite (the record
names them).

    python benchmarks/suite_profile.py                      # the whole suite, about 19 min on 2 cores
    python benchmarks/suite_profile.py -- tests/test_identify.py
"""

import argparse
import collections
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import machine, write  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--top", type=int, default=15, help="rows per table in the markdown")
    parser.add_argument("pytest_args", nargs="*", help="test paths and pytest options (after --)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        out = pathlib.Path(folder) / "events.jsonl"
        path = [p for p in (str(ROOT / "benchmarks"), os.environ.get("PYTHONPATH", "")) if p]
        env = dict(os.environ, SUITE_PROFILE_OUT=str(out), PYTHONPATH=os.pathsep.join(path))
        started = time.perf_counter()
        command = [sys.executable, "-m", "pytest", "-q", "-p", "no:xdist", "-p", "_compile_events"]
        done = subprocess.run(command + args.pytest_args, cwd=ROOT, env=env)
        wall = time.perf_counter() - started
        tests = [json.loads(line) for line in out.read_text().splitlines()] if out.exists() else []
    report(tests, args.pytest_args, done.returncode, wall, machine(), top=args.top)


def report(
    tests: list[dict], pytest_args: list[str], status: int, wall: float, where: dict, *, top: int = 15
) -> None:
    """Write the JSON and markdown of the per-test records `tests` (as the plugin writes them)."""
    modules = collections.defaultdict(collections.Counter)
    functions = collections.defaultdict(collections.Counter)
    for t in tests:
        module = t["test"].split("::")[0]
        for key in ("seconds", "compile_s", "trace_s", "lower_s", "compilations"):
            modules[module][key] += t[key]
        for name, (seconds, count) in t["compiled"].items():
            functions[name]["compile_s"] += seconds
            functions[name]["compilations"] += count
    totals = {key: sum(t[key] for t in tests) for key in ("seconds", "compile_s", "trace_s", "lower_s")}
    maps = [t["maps"] for t in tests if t.get("maps") is not None]
    result = {
        "benchmark": "suite_profile",
        "machine": where,
        "pytest_args": pytest_args,
        "exit_status": status,
        "wall_s": wall,
        "tests": len(tests),
        "totals": totals,
        # the most memory maps the process held after a test, and Linux's limit: past it XLA dies of a
        # segmentation fault (tests/conftest.py clears JAX's caches after a module above half of it)
        "memory_maps": {"most": max(maps, default=None), "limit": _map_limit()},
        "modules": {m: dict(c) for m, c in sorted(modules.items(), key=lambda kv: -kv[1]["seconds"])},
        "functions": {f: dict(c) for f, c in sorted(functions.items(), key=lambda kv: -kv[1]["compile_s"])},
        # the tests of a second or more, each with its five largest compilations (the totals above
        # count every test and compilation)
        "per_test": [
            dict(t, compiled=dict(list(t["compiled"].items())[:5]))
            for t in sorted(tests, key=lambda t: -t["seconds"])
            if t["seconds"] >= 1.0
        ],
    }
    share = lambda part: f"{100 * part / max(totals['seconds'], 1e-9):.0f}%"
    lines = [
        "# Where the test suite's time goes",
        "",
        f"{len(tests)} tests in one process ({' '.join(pytest_args) or 'the whole suite'}), "
        f"{wall:.0f} s; "
        f"tests {totals['seconds']:.0f} s, of which XLA compiling {totals['compile_s']:.0f} s "
        f"({share(totals['compile_s'])}), tracing {totals['trace_s']:.0f} s ({share(totals['trace_s'])}, "
        f"nested traces count twice), lowering {totals['lower_s']:.0f} s ({share(totals['lower_s'])}). "
        "Written by `benchmarks/suite_profile.py`.",
    ]
    if result["memory_maps"]["most"] is not None:
        lines += [
            "",
            f"Memory maps: at most {result['memory_maps']['most']} after a test, of Linux's "
            f"{result['memory_maps']['limit']} (`vm.max_map_count`; each compiled program JAX keeps holds "
            "three, and `tests/conftest.py` clears JAX's caches after a module above half the limit).",
        ]
    lines += [
        "",
        "| module | seconds | compile | trace | lower | compilations |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for module, c in list(result["modules"].items())[:top]:
        lines.append(
            f"| `{module}` | {c['seconds']:.1f} | {c['compile_s']:.1f} | {c['trace_s']:.1f} | "
            f"{c['lower_s']:.1f} | {c['compilations']} |"
        )
    lines += ["", "| test | seconds | compile | largest compilations |", "| --- | --- | --- | --- |"]
    for t in result["per_test"][:top]:
        largest = ", ".join(f"`{n}` {s:.1f} s" for n, (s, _) in list(t["compiled"].items())[:3])
        lines.append(f"| `{t['test']}` | {t['seconds']:.1f} | {t['compile_s']:.1f} | {largest} |")
    lines += ["", "| compiled function | compile seconds | compilations |", "| --- | --- | --- |"]
    for name, c in list(result["functions"].items())[:top]:
        lines.append(f"| `{name}` | {c['compile_s']:.1f} | {c['compilations']} |")
    keys = ("pytest_args", "exit_status", "wall_s", "tests", "totals", "memory_maps")
    summary = {key: result[key] for key in keys}
    write("suite_profile", result, "\n".join(lines) + "\n")
    print(json.dumps(summary, indent=2), file=sys.stderr)


def _map_limit() -> int | None:
    try:
        return int(pathlib.Path("/proc/sys/vm/max_map_count").read_text())
    except (OSError, ValueError):
        return None


if __name__ == "__main__":
    main()
