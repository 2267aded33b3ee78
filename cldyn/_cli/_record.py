"""`cldyn record`: MuJoCo trajectories of a scene to an `.npz` file (`cldyn.Sequences`)."""

import argparse

from ._common import CommandError, add_command, add_overwrite, finite, output_file, positive, seed

MJCF_HELP = (
    "an MJCF file, a dm_control suite name (acrobot, cartpole, ...), cartpole/two_poles or "
    "cartpole/three_poles (the suite's cart-poles with more poles) or keycld/<pendulum|cartpole|acrobot>"
)
INTEGRATORS = ("euler", "rk4", "implicit", "implicitfast")


def register(subparsers) -> None:
    """Add `cldyn record`."""
    parser = add_command(
        subparsers,
        "record",
        help="record trajectories of a MuJoCo scene to an .npz file",
        description="Record MuJoCo trajectories (joint and keypoint coordinates, controls, forces). By "
        "default KeyCLD's protocol: random initial joint positions and small velocities, one random "
        "constant control per run within the control range, zero in 20% of the runs.",
    )
    parser.add_argument("--mjcf", required=True, help=MJCF_HELP)
    parser.add_argument("--out", required=True, help="the .npz file to write (.npz is appended if missing)")
    parser.add_argument("--runs", type=positive(integer=True), default=500, help="number of runs")
    parser.add_argument("--duration", type=positive(), default=1.0, help="seconds per run")
    parser.add_argument(
        "--dt", type=positive(), default=None, help="sampling interval (default: the model's timestep)"
    )
    parser.add_argument(
        "--noise", type=positive(allow_zero=True), default=0.0, help="std of keypoint position noise (m)"
    )
    parser.add_argument("--seed", type=seed, default=0, help="random seed")
    parser.add_argument(
        "--physics-dt",
        type=positive(),
        default=None,
        help="MuJoCo's step, dividing dt (default: the largest step not above the model's timestep)",
    )
    parser.add_argument(
        "--integrator", choices=INTEGRATORS, default=None, help="MuJoCo's integrator (default: the model's)"
    )
    parser.add_argument(
        "--keypoints",
        nargs="+",
        default=None,
        metavar="SITE",
        help="sites to use as keypoints (default: from_mjcf's, the moving joints' anchors and tips)",
    )
    parser.add_argument(
        "--control-range",
        type=finite,
        nargs=2,
        default=None,
        metavar=("LOW", "HIGH"),
        help="range of the random controls (default: ctrlrange, or -2 2 where unlimited)",
    )
    add_overwrite(parser, "a recording")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Record, save, print one line."""
    if args.control_range is not None:
        low, high = args.control_range
        if not low < high:
            raise CommandError(f"--control-range {low:g} {high:g}: need LOW < HIGH")
    out = output_file(args.out, suffix=".npz", overwrite=args.overwrite)
    from cldyn.mujoco import record

    from .. import TqdmProgressMeter

    data = record(
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
        progress_meter=TqdmProgressMeter(),
    )
    path = data.save(out, overwrite=args.overwrite)
    info = data.info
    print(
        f"recorded {data.num_runs} runs x {data.num_samples} samples (dt {data.dt:g} s, "
        f"MuJoCo {info['integrator']} at {info['physics_dt']:g} s) of {info['mjcf']}; "
        f"keypoints {list(info['keypoint_names'])}; wrote {path}"
    )
    return 0
