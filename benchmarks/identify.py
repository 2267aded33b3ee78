"""Finding missing physics on mechanisms built for the purpose, at any sampling rate and noise.

Three mechanisms that are not KeyCLD scenes (benchmarks/mechanisms/): a pendulum with a tip mass, a
cart-pole whose pole carries its mass along its length, a double pendulum with both joints actuated;
their own masses, lengths, gears and control ranges (clamped by MuJoCo), MuJoCo's default Euler at
0.5 ms. Into each, effects are injected one at a time (damping, frictionloss with MuJoCo's constraints
on, a spring with springref, armature, a gear error) and two at once (damping on one joint, a spring
on another); the data are recorded as `cldyn record` records them (`cldyn.mujoco.record` with the
command's defaults: 40 runs, random initial states, one random constant control per run, physics at
the model's timestep) at dt = 0.5, 2, 10 and 20 ms with 0 and 1 mm of position noise (and 3 mm for
damping), runs of 2 s (and 1 s and 4 s for damping at 1 mm), and identified against the nominal MJCF
as `cldyn identify` does (`identify_recording` with its defaults). Effect-free data of every
mechanism, rate and noise level, 10 seeds each, are the negative control.

A cell passes when every injected effect is detected at its joint or actuator with its value within
15% (30% for frictionloss) and the held-out 1 s rollout error drops at least 5x; other detections are
listed. Every cell is reported, misses included.

Writes benchmarks/results/identify.json and identify.md; prints the JSON. While it runs, each cell is
appended to identify.jsonl as it finishes: an interrupted run resumes from it (and a partial run, with
--only and the like, from identify.json), --fresh starts over, and --rerun runs the selected cells again
while every other cell keeps its row (after a change that concerns some of them).

    python benchmarks/identify.py                 # everything (hours on 2 cores)
    python benchmarks/identify.py --only pendulum_tip --dt 0.002 --noise 0.001
    python benchmarks/identify.py --only double_pendulum --dt 0.02 --rerun   # refresh these cells
"""

import argparse
import gc
import json
import os
import pathlib
import sys
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import jax

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from _common import RESULTS, machine, write  # noqa: E402

jax.config.update("jax_enable_x64", True)

from cldyn.mujoco import identify_recording, modify_scene, record  # noqa: E402

MECHANISMS = ROOT / "benchmarks" / "mechanisms"
RATES = (0.0005, 0.002, 0.01, 0.02)
NOISES = (0.0, 0.001)
DAMPING_NOISE = 0.003
DURATION = 2.0
DURATIONS = (1.0, 4.0)  # damping cases at 1 mm, besides 2 s
RUNS = 40
NEGATIVE_SEEDS = range(100, 110)
VALUE_RTOL, FRICTION_RTOL, MIN_DROP = 0.15, 0.30, 5.0
FRICTION = {"constraint": "enable", "frictionloss": "enable"}

# (mechanism, case name, modify_scene changes, {(effect, where): true value}); springref in degrees
CASES = [
    ("pendulum_tip", "damping", {"joints": {"pivot": {"damping": 0.15}}}, {("joint_damping", "pivot"): 0.15}),
    (
        "pendulum_tip",
        "frictionloss",
        {"joints": {"pivot": {"frictionloss": 0.4}}, "flags": FRICTION},
        {("joint_coulomb", "pivot"): 0.4},
    ),
    (
        "pendulum_tip",
        "spring",
        {"joints": {"pivot": {"stiffness": 20.0, "springref": 15.0}}},
        {("joint_spring", "pivot"): 20.0},
    ),
    (
        "pendulum_tip",
        "armature",
        {"joints": {"pivot": {"armature": 0.1}}},
        {("joint_armature", "pivot"): 0.1},
    ),
    ("pendulum_tip", "gear", {"actuators": {"drive": {"gear": 3.6}}}, {("actuator_gain", "drive"): 1.2}),
    ("cartpole_pole", "damping", {"joints": {"rail": {"damping": 2.0}}}, {("joint_damping", "rail"): 2.0}),
    (
        "cartpole_pole",
        "frictionloss",
        {"joints": {"rail": {"frictionloss": 1.0}}, "flags": FRICTION},
        {("joint_coulomb", "rail"): 1.0},
    ),
    (
        "cartpole_pole",
        "spring",
        {"joints": {"rail": {"stiffness": 10.0, "springref": 0.2}}},
        {("joint_spring", "rail"): 10.0},
    ),
    (
        "cartpole_pole",
        "armature",
        {"joints": {"swivel": {"armature": 0.02}}},
        {("joint_armature", "swivel"): 0.02},
    ),
    ("cartpole_pole", "gear", {"actuators": {"push": {"gear": 10.8}}}, {("actuator_gain", "push"): 0.9}),
    (
        "cartpole_pole",
        "damping+spring",
        {"joints": {"swivel": {"damping": 0.05}, "rail": {"stiffness": 10.0, "springref": 0.2}}},
        {("joint_damping", "swivel"): 0.05, ("joint_spring", "rail"): 10.0},
    ),
    (
        "double_pendulum",
        "damping",
        {"joints": {"elbow": {"damping": 0.1}}},
        {("joint_damping", "elbow"): 0.1},
    ),
    (
        "double_pendulum",
        "frictionloss",
        {"joints": {"shoulder": {"frictionloss": 0.5}}, "flags": FRICTION},
        {("joint_coulomb", "shoulder"): 0.5},
    ),
    (
        "double_pendulum",
        "spring",
        {"joints": {"shoulder": {"stiffness": 30.0, "springref": 20.0}}},
        {("joint_spring", "shoulder"): 30.0},
    ),
    (
        "double_pendulum",
        "armature",
        {"joints": {"elbow": {"armature": 0.05}}},
        {("joint_armature", "elbow"): 0.05},
    ),
    (
        "double_pendulum",
        "gear",
        {"actuators": {"elbow_motor": {"gear": 2.5}}},
        {("actuator_gain", "elbow_motor"): 1.25},
    ),
    (
        "double_pendulum",
        "damping+spring",
        {"joints": {"elbow": {"damping": 0.1}, "shoulder": {"stiffness": 30.0, "springref": 20.0}}},
        {("joint_damping", "elbow"): 0.1, ("joint_spring", "shoulder"): 30.0},
    ),
]


def nominal(mechanism: str) -> str:
    return str(MECHANISMS / f"{mechanism}.xml")


def cells(args):
    """Every cell of the matrix: (key, mechanism, case, changes, truth, dt, noise, duration, seed)."""
    out = []
    for index, (mechanism, case, changes, truth) in enumerate(CASES):
        noises = NOISES + ((DAMPING_NOISE,) if case == "damping" else ())
        for dt in RATES:
            for noise in noises:
                out.append((mechanism, case, changes, truth, dt, noise, DURATION, index))
            if case == "damping":
                for duration in DURATIONS:
                    out.append((mechanism, case, changes, truth, dt, 0.001, duration, index))
    for mechanism in ("pendulum_tip", "cartpole_pole", "double_pendulum"):
        for dt in RATES:
            for noise in NOISES + (DAMPING_NOISE,):
                for seed in NEGATIVE_SEEDS:
                    out.append((mechanism, "none", {}, {}, dt, noise, DURATION, seed))
    keep = []
    for cell in out:
        mechanism, case, _, _, dt, noise, duration, _ = cell
        if args.only and mechanism not in args.only:
            continue
        if args.case and case not in args.case:
            continue
        if args.dt and dt not in args.dt:
            continue
        if args.noise is not None and noise not in args.noise:
            continue
        keep.append(cell)
    return keep


def key(cell) -> str:
    mechanism, case, _, _, dt, noise, duration, seed = cell
    return f"{mechanism}|{case}|{dt:g}|{noise:g}|{duration:g}|{seed}"


def run_cell(cell) -> dict:
    mechanism, case, changes, truth, dt, noise, duration, seed = cell
    xml = modify_scene(nominal(mechanism), **changes) if changes else nominal(mechanism)
    started = time.perf_counter()
    data = record(xml, duration=duration, dt=dt, runs=RUNS, noise=noise, seed=seed)
    recorded = time.perf_counter() - started
    result = identify_recording(data, nominal(mechanism))
    found = {(d.name, d.where): d for d in result.detected}
    effects = []
    ok = True
    for (effect, where), value in truth.items():
        d = found.get((effect, where))
        rtol = FRICTION_RTOL if effect == "joint_coulomb" else VALUE_RTOL
        error = None if d is None else abs(d.value - value) / value
        hit = d is not None and error <= rtol
        ok &= hit
        effects.append(
            {
                "effect": effect,
                "where": where,
                "truth": value,
                "value": None if d is None else d.value,
                "ci": None if d is None else list(d.ci),
                "relative_error": error,
                "parameters": None if d is None else d.parameters,
                "within_tolerance": bool(hit),
            }
        )
    drop = result.before.rollout_rmse_1s / result.after.rollout_rmse_1s
    others = [d.candidate.label for d in result.detected if (d.name, d.where) not in truth]
    sm = result.settings["smoothing"]
    return {
        "key": key(cell),
        "mechanism": mechanism,
        "case": case,
        "dt": dt,
        "noise": noise,
        "duration": duration,
        "seed": seed,
        "effects": effects,
        "others": others,
        "outcome": result.outcome,
        "rollout_before_m": result.before.rollout_rmse_1s,
        "rollout_after_m": result.after.rollout_rmse_1s,
        "rollout_drop": drop,
        "passed": bool(ok and drop >= MIN_DROP and not others) if truth else not result.detected,
        "smoothing": {
            k: sm[k] for k in ("noise", "timescale_seconds", "window_seconds", "test_width_seconds")
        }
        | {"interval_seconds": sm["interval_seconds"]},
        "detectable_share": result.adequacy.detectable_share,
        "problems": list(result.adequacy.problems),
        "warnings": list(result.warnings),
        "record_seconds": recorded,
        "identify_seconds": result.settings["seconds"],
    }


def _ms(dt: float) -> str:
    return f"{1e3 * dt:g} ms"


def _number(value) -> str:
    return "-" if value is None else f"{value:.4g}"


def _percent(value) -> str:
    return "-" if value is None else f"{100 * value:.1f}%"


def markdown(rows: list[dict]) -> str:
    positives = [r for r in rows if r["case"] != "none"]
    lines = [
        "# Finding missing physics at any rate and noise (issue 11)",
        "",
        "Mechanisms built for the purpose (`benchmarks/mechanisms/`), effects injected with "
        "`modify_scene`, recorded as `cldyn record` does (40 runs, MuJoCo Euler at 0.5 ms) and identified as "
        "`cldyn identify` does (settings chosen from the data). A cell passes when every injected effect is "
        f"found at its joint or actuator within {100 * VALUE_RTOL:.0f}% ({100 * FRICTION_RTOL:.0f}% for "
        f"frictionloss), the held-out 1 s rollout error drops at least {MIN_DROP:g}x, and nothing else is "
        "detected. `time` is identify's wall time (compilation included where a shape is new to the "
        "process).",
        "",
        "| mechanism | case | dt | noise | runs of | found (truth) | error | rollout 1 s before -> after | "
        "drop | others | window / test / kept every | time | pass |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in positives:
        found = "; ".join(
            f"{e['effect']}[{e['where']}] {_number(e['value'])} ({e['truth']:g})" for e in r["effects"]
        )
        error = "; ".join(_percent(e["relative_error"]) for e in r["effects"])
        sm = r["smoothing"]
        lines.append(
            f"| {r['mechanism']} | {r['case']} | {_ms(r['dt'])} | {1e3 * r['noise']:g} mm | "
            f"{r['duration']:g} s | "
            f"{found} | {error} | {1e3 * r['rollout_before_m']:.3g} -> {1e3 * r['rollout_after_m']:.3g} mm | "
            f"{r['rollout_drop']:.1f}x | {', '.join(r['others']) or '-'} | "
            f"{1e3 * sm['window_seconds']:.0f} / {1e3 * sm['test_width_seconds']:.0f} / "
            f"{1e3 * sm['interval_seconds']:.3g} ms | {r['identify_seconds']:.1f} s | "
            f"{'yes' if r['passed'] else '**no**'} |"
        )
    passed = sum(r["passed"] for r in positives)
    lines += ["", f"Injected effects: {passed} of {len(positives)} cells pass.", ""]
    if positives:
        errors = [e["relative_error"] for r in positives for e in r["effects"]]
        errors = [e for e in errors if e is not None]
        drops = [r["rollout_drop"] for r in positives]
        times = sorted(r["identify_seconds"] for r in rows)
        positive_times = sorted(r["identify_seconds"] for r in positives)
        lines += [
            f"Largest relative error of a value found: {100 * max(errors):.1f}%; held-out rollout error "
            f"drops {min(drops):.1f}x to {max(drops):,.0f}x. identify's wall time per data set: median "
            f"{positive_times[len(positive_times) // 2]:.1f} s with an effect, "
            f"{times[len(times) // 2]:.1f} s over every cell, at most {times[-1]:.0f} s (first compilations "
            "in a process included, on a 2-core CPU shared with other work).",
            "",
        ]
    negatives = [r for r in rows if r["case"] == "none"]
    if negatives:
        lines += [
            "Negative control: effect-free data, 10 seeds per mechanism, rate and noise; seeds in which "
            "something was detected:",
            "",
            "| mechanism | dt | noise | false detections | outcome | what |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        groups: dict[tuple, list[dict]] = {}
        for r in negatives:
            groups.setdefault((r["mechanism"], r["dt"], r["noise"]), []).append(r)
        for (mechanism, dt, noise), group in groups.items():
            false = [r for r in group if not r["passed"]]
            what = "; ".join(f"seed {r['seed']}: {', '.join(o for o in r['others'])}" for r in false) or "-"
            outcomes = sorted({r["outcome"] for r in group})
            lines.append(
                f"| {mechanism} | {_ms(dt)} | {1e3 * noise:g} mm | {len(false)} of {len(group)} | "
                f"{', '.join(outcomes)} | {what} |"
            )
        lines.append("")
    agreement = rate_agreement(positives)
    if agreement:
        lines += [
            "Same motion (same seed) sampled at 0.5 ms and at 10 ms: relative difference of the values "
            "found.",
            "",
            "| mechanism | case | noise | effect | 0.5 ms | 10 ms | difference |",
            "| --- | --- | --- | --- | --- | --- | --- |",
        ]
        for a in agreement:
            lines.append(
                f"| {a['mechanism']} | {a['case']} | {1e3 * a['noise']:g} mm | {a['effect']} | "
                f"{a['fast']:.4g} | {a['slow']:.4g} | {100 * a['difference']:.2f}% |"
            )
        lines.append("")
    return "\n".join(lines)


def rate_agreement(rows: list[dict]) -> list[dict]:
    out = []
    index = {(r["mechanism"], r["case"], r["dt"], r["noise"], r["duration"]): r for r in rows}
    for (mechanism, case, dt, noise, duration), fast in index.items():
        if dt != 0.0005 or duration != DURATION:
            continue
        slow = index.get((mechanism, case, 0.01, noise, duration))
        if slow is None:
            continue
        for a, b in zip(fast["effects"], slow["effects"]):
            if a["value"] is None or b["value"] is None:
                continue
            out.append(
                {
                    "mechanism": mechanism,
                    "case": case,
                    "noise": noise,
                    "effect": f"{a['effect']}[{a['where']}]",
                    "fast": a["value"],
                    "slow": b["value"],
                    "difference": abs(a["value"] - b["value"]) / abs(a["value"]),
                }
            )
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="+", help="mechanisms")
    parser.add_argument("--case", nargs="+", help="cases (damping, ..., none for the negative control)")
    parser.add_argument("--dt", nargs="+", type=float, help="sampling intervals")
    parser.add_argument("--noise", nargs="+", type=float, help="noise levels")
    parser.add_argument("--fresh", action="store_true", help="ignore the results of an earlier run")
    parser.add_argument(
        "--rerun",
        action="store_true",
        help="run the selected cells again (resuming an interrupted rerun), keeping the other cells' rows",
    )
    args = parser.parse_args()
    if args.fresh and args.rerun:
        parser.error("--fresh drops every earlier cell and --rerun keeps the unselected ones: choose one")
    journal = RESULTS / "identify.jsonl"
    done = {}
    if args.fresh:
        journal.unlink(missing_ok=True)
    else:
        # the cells of the last complete run (less those to run again), and those of an interrupted one
        if (RESULTS / "identify.json").exists():
            done = {row["key"]: row for row in json.loads((RESULTS / "identify.json").read_text())["cells"]}
        if args.rerun:
            selected = {key(cell) for cell in cells(args)}
            done = {k: row for k, row in done.items() if k not in selected}
        if journal.exists():
            done |= {row["key"]: row for row in map(json.loads, journal.read_text().splitlines())}
    started = time.perf_counter()
    todo = cells(args)
    previous = None
    for count, cell in enumerate(todo, 1):
        if key(cell) in done:
            continue
        if previous is not None and (cell[0], cell[1]) != previous:
            # compiled programs pile up (every new shape and model is one): a case's are of little use
            # to the next, and a long run would otherwise exhaust the memory
            jax.clear_caches()
            gc.collect()
        previous = (cell[0], cell[1])
        row = run_cell(cell)
        done[row["key"]] = row
        with journal.open("a") as f:
            f.write(json.dumps(row) + "\n")
        print(
            f"[{count}/{len(todo)}] {row['key']}: {'pass' if row['passed'] else 'MISS'} "
            f"{[(e['effect'], e['value']) for e in row['effects']]} others {row['others']} "
            f"drop {row['rollout_drop']:.1f}x {row['identify_seconds']:.1f} s",
            file=sys.stderr,
            flush=True,
        )
    order = {
        key(c): i for i, c in enumerate(cells(argparse.Namespace(only=None, case=None, dt=None, noise=None)))
    }
    rows = sorted(done.values(), key=lambda r: order.get(r["key"], len(order)))
    result = {
        "benchmark": "identify",
        "cells": rows,
        "rate_agreement": rate_agreement([r for r in rows if r["case"] != "none"]),
        "seconds": time.perf_counter() - started,
        "record_seconds_total": sum(r["record_seconds"] for r in rows),
        "identify_seconds_total": sum(r["identify_seconds"] for r in rows),
        "machine": machine(),
    }
    write("identify", result, markdown(rows))
    journal.unlink(missing_ok=True)


if __name__ == "__main__":
    main()
