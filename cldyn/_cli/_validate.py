"""`cldyn validate`: `from_mjcf`'s cldyn model against MuJoCo on random motions."""

import argparse
import json

from ._common import (
    CommandError,
    add_command,
    add_overwrite,
    enable_float64,
    output_directory,
    positive,
    seed,
)
from ._record import MJCF_HELP

# The report's entries printed as the one-line JSON summary.
SUMMARY = (
    "mjcf",
    "include",
    "runs",
    "duration",
    "physics_dt",
    "max_position_error",
    "max_velocity_error",
    "mujoco_constraints_active",
)


def register(subparsers) -> None:
    """Add `cldyn validate`."""
    parser = add_command(
        subparsers,
        "validate",
        help="compare from_mjcf's cldyn model with MuJoCo on random motions",
        description="Simulate the MJCF in MuJoCo (RK4, small step) and its from_mjcf model in cldyn "
        "(float64, tight tolerances) from the same random initial states and constant controls; write "
        "validation.json and a plot of the keypoint error over time.",
    )
    parser.add_argument("--mjcf", required=True, help=MJCF_HELP)
    parser.add_argument("--out", required=True, help="directory for validation.json and the plot")
    parser.add_argument(
        "--include",
        nargs="*",
        default=[],
        metavar="EFFECT",
        help="passive effects to model: damping, stiffness, armature (default: none)",
    )
    parser.add_argument(
        "--keypoints",
        nargs="+",
        default=None,
        metavar="SITE",
        help="sites to use as keypoints (default: from_mjcf's, the moving joints' anchors and tips)",
    )
    parser.add_argument("--runs", type=positive(integer=True), default=10, help="number of runs")
    parser.add_argument("--duration", type=positive(), default=2.0, help="seconds per run")
    parser.add_argument("--dt", type=positive(), default=0.01, help="comparison interval (s)")
    parser.add_argument("--physics-dt", type=positive(), default=1e-4, help="MuJoCo's RK4 step (s)")
    parser.add_argument("--seed", type=seed, default=0, help="random seed")
    parser.add_argument(
        "--joint-limits",
        action="store_true",
        help="keep MuJoCo's joint limits (from_mjcf does not model them)",
    )
    parser.add_argument(
        "--tolerance",
        type=positive(),
        default=None,
        help="exit with status 1 if the max position error exceeds this (metres; default: no check)",
    )
    add_overwrite(parser, "validation.json and the plot")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Validate, print the summary; status 1 above `--tolerance`."""
    if args.duration < args.dt:
        raise CommandError(
            f"--duration {args.duration:g}: shorter than --dt {args.dt:g}, so nothing would be compared"
        )
    from cldyn._misc import VALIDATION_PLOT as PLOT_NAME, VALIDATION_REPORT as REPORT_NAME

    out = output_directory(args.out, results=(REPORT_NAME, PLOT_NAME), overwrite=args.overwrite)
    enable_float64()
    from cldyn.mujoco import validate

    from .. import TqdmProgressMeter

    report = validate(
        args.mjcf,
        out=out,
        include=tuple(args.include),
        keypoints=args.keypoints,
        runs=args.runs,
        duration=args.duration,
        dt=args.dt,
        physics_dt=args.physics_dt,
        seed=args.seed,
        joint_limits=args.joint_limits,
        progress_meter=TqdmProgressMeter(),
    )
    print(json.dumps({key: report[key] for key in SUMMARY}))
    print(
        f"max keypoint position error {report['max_position_error']:.3g} m over {report['runs']} runs "
        f"of {report['duration']:g} s; wrote {out / REPORT_NAME} and {out / PLOT_NAME}"
    )
    if args.tolerance is not None and not report["max_position_error"] <= args.tolerance:
        print(f"FAILED: above the tolerance {args.tolerance:g} m")
        return 1
    return 0
