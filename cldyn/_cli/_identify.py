"""`cldyn identify`: find the physics a nominal MJCF model is missing in recorded data."""

import argparse

from ._common import (
    add_command,
    add_overwrite,
    enable_float64,
    fraction,
    input_file,
    output_directory,
    positive,
    seed,
)

# what Identification.save writes
REPORT_FILES = ("report.json", "report.md", "error_over_time.png", "residual_vs_feature.png")


def register(subparsers) -> None:
    """Add `cldyn identify`."""
    from .. import EFFECTS, Smoothing

    effects = [effect.name for effect in EFFECTS]

    parser = add_command(
        subparsers,
        "identify",
        help="find the physics a nominal MJCF model is missing in recorded data",
        description=(
            "Compute the residual of the nominal model on recorded data, attribute it to effects of the "
            "library (damping, Coulomb friction, springs, armature, actuator gain, drag, point masses), "
            "add them, refit, and report the error before and after."
        ),
    )
    parser.add_argument("--data", required=True, help="a recording saved by `cldyn record` (.npz)")
    parser.add_argument("--model", required=True, help="the nominal MJCF (file, suite name or keycld/<name>)")
    parser.add_argument("--out", required=True, help="directory for report.json/md and plots")
    parser.add_argument(
        "--effects",
        nargs="+",
        default=effects,
        choices=effects,
        metavar="EFFECT",
        help=f"effects to consider, of {', '.join(effects)} (default: all)",
    )
    count = positive(integer=True)
    parser.add_argument("--bootstrap", type=count, default=100, help="bootstrap replicates")
    parser.add_argument("--holdout", type=fraction, default=0.25, help="fraction of runs held out")
    parser.add_argument("--max-rounds", type=count, default=3, help="detect-augment-refit rounds")
    parser.add_argument(
        "--window", type=count, default=Smoothing.window, help="Savitzky-Golay window (samples)"
    )
    parser.add_argument(
        "--order",
        type=positive(integer=True, allow_zero=True),
        default=Smoothing.order,
        help="Savitzky-Golay polynomial order",
    )
    parser.add_argument("--test-width", type=count, default=Smoothing.test_width, help="test function width")
    parser.add_argument(
        "--test-stride", type=count, default=Smoothing.test_stride, help="test function stride"
    )
    parser.add_argument("--seed", type=seed, default=0, help="seed of the split and the bootstrap")
    add_overwrite(parser, "a report")
    parser.set_defaults(run=run)


def narrative(result, samples: int) -> str:
    """What the identification did, round by round, as `cldyn identify` has always printed it.

    `samples` is the length of each run as measured (the settings record the smoothing window, whose
    ends the residual leaves out)."""
    settings = result.settings
    runs, held = settings["runs"], len(settings["held_out_runs"])
    used = samples - (settings["smoothing"]["window"] - 1)

    def errors(name, e):
        return f"  {name}: accel_rmse {e.accel_rmse:.4g} m/s^2, rollout_rmse_1s {e.rollout_rmse_1s:.4g} m"

    lines = [f"identify: {runs} runs ({runs - held} fit, {held} held out), {used} samples each"]
    lines.append(errors("before", result.before))
    lines += [f"  round {r.round}: " + ("; ".join(r.detected) or "nothing passes") for r in result.rounds]
    lines.append(errors("after", result.after))
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Identify, save the report, print its summary."""
    path = input_file(args.data, "--data")
    out = output_directory(args.out, results=REPORT_FILES, overwrite=args.overwrite)
    enable_float64()
    import cldyn
    from cldyn.mujoco import identify_recording

    data = cldyn.Sequences.load(path)
    result = identify_recording(
        data,
        args.model,
        effects=tuple(args.effects),
        smoothing=cldyn.Smoothing(
            window=args.window, order=args.order, test_width=args.test_width, test_stride=args.test_stride
        ),
        criteria=cldyn.Criteria(),
        bootstrap=args.bootstrap,
        holdout=args.holdout,
        max_rounds=args.max_rounds,
        seed=args.seed,
        progress_meter=cldyn.TqdmProgressMeter(),
    )
    report = result.save(out)
    print(narrative(result, data.num_samples))
    print(result.summary())
    print(f"wrote {report / 'report.json'}, {report / 'report.md'} and plots")
    return 0
