"""`cldyn record` and `cldyn validate`: the MuJoCo bridge on the command line."""

import argparse
import json
import pathlib

_MJCF_HELP = (
    "an MJCF file, a dm_control suite name (acrobot, cartpole, ...) or keycld/<pendulum|cartpole|acrobot>"
)


def _record(args: argparse.Namespace) -> int:
    from ._record import record

    recording = record(
        args.mjcf,
        duration=args.duration,
        dt=args.dt,
        runs=args.runs,
        keypoints=args.keypoints,
        noise=args.noise,
        seed=args.seed,
        physics_dt=args.physics_dt,
        integrator=args.integrator,
        control_range=args.control_range,
        progress=True,
    )
    path = recording.save(args.out)
    print(
        f"recorded {recording.num_runs} runs x {recording.num_samples} samples (dt {recording.dt:g} s, "
        f"MuJoCo {recording.integrator} at {recording.physics_dt:g} s) of {recording.mjcf}; "
        f"keypoints {list(recording.keypoint_names)}; wrote {path}"
    )
    return 0


def _validate(args: argparse.Namespace) -> int:
    from ._validate import PLOT_NAME, REPORT_NAME, validate

    report = validate(
        args.mjcf,
        out=args.out,
        include=tuple(args.include),
        keypoints=args.keypoints,
        runs=args.runs,
        duration=args.duration,
        dt=args.dt,
        physics_dt=args.physics_dt,
        seed=args.seed,
        joint_limits=args.joint_limits,
        progress=True,
    )
    out = pathlib.Path(args.out)
    summary = {
        key: report[key]
        for key in (
            "mjcf",
            "include",
            "runs",
            "duration",
            "physics_dt",
            "max_position_error",
            "max_velocity_error",
            "mujoco_constraints_active",
        )
    }
    print(json.dumps(summary))
    print(
        f"max keypoint position error {report['max_position_error']:.3g} m over {report['runs']} runs "
        f"of {report['duration']:g} s; wrote {out / REPORT_NAME} and {out / PLOT_NAME}"
    )
    if args.tolerance is not None and not report["max_position_error"] <= args.tolerance:
        print(f"FAILED: above the tolerance {args.tolerance:g} m")
        return 1
    return 0


def register(subparsers) -> None:
    """Add the `record` and `validate` commands to the `cldyn` command line."""
    record = subparsers.add_parser(
        "record",
        help="record trajectories of a MuJoCo scene to an .npz file",
        description="Record MuJoCo trajectories (joint and keypoint coordinates, controls, forces). By "
        "default KeyCLD's protocol: random initial joint positions and small velocities, one random "
        "constant control per run within the control range, zero in 20%% of the runs.",
    )
    record.add_argument("--mjcf", required=True, help=_MJCF_HELP)
    record.add_argument("--out", required=True, help="the .npz file to write")
    record.add_argument("--runs", type=int, default=500, help="number of runs (default 500)")
    record.add_argument("--duration", type=float, default=1.0, help="seconds per run (default 1)")
    record.add_argument(
        "--dt", type=float, default=None, help="sampling interval (default: the model's timestep)"
    )
    record.add_argument("--noise", type=float, default=0.0, help="std of keypoint position noise in metres")
    record.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    record.add_argument("--physics-dt", type=float, default=None, help="MuJoCo step dividing dt")
    record.add_argument("--integrator", default=None, help="euler, rk4, implicit or implicitfast")
    record.add_argument(
        "--keypoints", nargs="+", default=None, metavar="SITE", help="sites to use as keypoints"
    )
    record.add_argument(
        "--control-range",
        type=float,
        nargs=2,
        default=None,
        metavar=("LOW", "HIGH"),
        help="range of the random controls (default: ctrlrange, or -2 2 where unlimited)",
    )
    record.set_defaults(run=_record)

    validate = subparsers.add_parser(
        "validate",
        help="compare from_mjcf's cldyn model with MuJoCo on random motions",
        description="Simulate the MJCF in MuJoCo (RK4, small step) and its from_mjcf model in cldyn "
        "(float64, tight tolerances) from the same random initial states and constant controls; write "
        "validation.json and a plot of the keypoint error over time.",
    )
    validate.add_argument("--mjcf", required=True, help=_MJCF_HELP)
    validate.add_argument("--out", required=True, help="directory for validation.json and the plot")
    validate.add_argument(
        "--include",
        nargs="*",
        default=[],
        metavar="EFFECT",
        help="passive effects to model: damping, stiffness, armature",
    )
    validate.add_argument(
        "--keypoints", nargs="+", default=None, metavar="SITE", help="sites to use as keypoints"
    )
    validate.add_argument("--runs", type=int, default=10, help="number of runs (default 10)")
    validate.add_argument("--duration", type=float, default=2.0, help="seconds per run (default 2)")
    validate.add_argument("--dt", type=float, default=0.01, help="comparison interval (default 0.01)")
    validate.add_argument("--physics-dt", type=float, default=1e-4, help="MuJoCo's RK4 step (default 1e-4)")
    validate.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    validate.add_argument(
        "--joint-limits",
        action="store_true",
        help="keep MuJoCo's joint limits (from_mjcf does not model them)",
    )
    validate.add_argument(
        "--tolerance",
        type=float,
        default=None,
        help="exit with status 1 if the max position error exceeds this (metres)",
    )
    validate.set_defaults(run=_validate)
