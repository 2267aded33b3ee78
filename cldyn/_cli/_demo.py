"""`cldyn demo`: the main job on an embedded default, with no arguments and no downloads.

MuJoCo plays reality: trajectories are recorded, with 1 mm position noise, from dm_control's stock
acrobot, whose joints carry a damping of 0.05 that the nominal model (the same MJCF through `from_mjcf`,
without `include`) does not declare. `cldyn identify` finds the residual, traces it to the missing
effect, adds it, refits, and reports the error before and after.
"""

import argparse
import time

from ._common import add_command, add_overwrite, enable_float64, output_directory, positive, seed
from ._identify import REPORT_FILES, narrative

SCENE = "acrobot"


def register(subparsers) -> None:
    """Add `cldyn demo`."""
    parser = add_command(
        subparsers,
        "demo",
        help="find the damping that dm_control's acrobot declares and its nominal model lacks",
        description=__doc__,
    )
    parser.add_argument("--out", default="demo_output", help="output directory")
    parser.add_argument("--runs", type=positive(integer=True), default=40, help="recorded runs")
    parser.add_argument("--duration", type=positive(), default=4.0, help="seconds per run")
    parser.add_argument("--noise", type=positive(allow_zero=True), default=1e-3, help="position noise (m)")
    parser.add_argument("--seed", type=seed, default=0, help="seed of the recording and the identification")
    add_overwrite(parser, "the recording and the report")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Record (100 Hz samples, MuJoCo RK4 at 2 ms, KeyCLD's random starts and constant controls),
    identify against the nominal model, save and print the report."""
    results = ("measured.npz",) + tuple(f"identify/{name}" for name in REPORT_FILES)
    out = output_directory(args.out, results=results, overwrite=args.overwrite)
    enable_float64()
    import cldyn
    from cldyn.mujoco import identify_recording, record

    started = time.perf_counter()
    print(
        f"[1/3] recording {args.runs} runs x {args.duration:g} s of dm_control's {SCENE!r} "
        f"(noise {1e3 * args.noise:g} mm)"
    )
    data = record(
        SCENE,
        runs=args.runs,
        duration=args.duration,
        dt=0.01,
        physics_dt=0.002,
        integrator="rk4",
        noise=args.noise,
        seed=args.seed,
        progress_meter=cldyn.TqdmProgressMeter(),
    )
    data.save(out / "measured.npz", overwrite=args.overwrite)
    print(f"[2/3] identifying what the nominal model of {SCENE!r} is missing")
    result = identify_recording(data, SCENE, seed=args.seed, progress_meter=cldyn.TqdmProgressMeter())
    print(narrative(result))
    print("[3/3] report")
    report = result.save(out / "identify")
    print(result.summary())
    print(f"wrote {out / 'measured.npz'}, {report / 'report.json'}, {report / 'report.md'},")
    print(f"      {report / 'error_over_time.png'} and {report / 'residual_vs_feature.png'}")
    print(f"done in {time.perf_counter() - started:.0f} s")
    return 0
