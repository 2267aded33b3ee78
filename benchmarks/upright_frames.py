"""Training frames that show the target: the paper's runs of a KeyCLD scene plus runs started near it.

The paper's protocol starts every run from hinge angles drawn over the whole circle, and the acrobot,
driven by a constant random control, then spends about 0.6% of its frames within 0.4 rad of upright,
the target of the swing-up (`docs/acrobot_from_frames.md`). This writes one frames file: the paper's
450 training runs, `--runs` more runs of the same protocol whose hinges start within `--angle` rad of
upright (`keyvision.RenderProtocol(angle_limit=)`; upright is `qpos = 0` in KeyCLD's scenes), then the
paper's 50 validation runs, unchanged, last. `keyvision train --data OUT` trains on the first two
parts and validates on the third, as on the paper's frames. Prints the share of frames near upright
in each part.

    python benchmarks/upright_frames.py --scene keycld/acrobot --out runs/upright/data
"""

import argparse
import os
import pathlib

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

NEAR = 0.4  # rad: a frame is near upright when every hinge is within this of it


def _near_share(frames) -> float:
    import cldyn

    info = frames.info
    hinges = [i for i, kind in zip(info["joint_qpos_index"], info["joint_types"]) if kind == "hinge"]
    q = frames.extras["qpos"][..., hinges]
    return float(np.mean(np.all(np.abs(np.asarray(cldyn.wrap_angle(q))) < NEAR, axis=-1)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="keycld/acrobot")
    parser.add_argument("--runs", type=int, default=150, help="runs started near upright")
    parser.add_argument("--angle", type=float, default=0.5, help="their hinges start in U(-angle, angle)")
    parser.add_argument("--seed", type=int, default=52, help="their seed (the paper's runs have seed 0)")
    parser.add_argument("--out", required=True, help="directory for frames.npz")
    args = parser.parse_args()

    import cldyn
    import keyvision

    meter = cldyn.TextProgressMeter()
    paper = keyvision.render(args.scene, progress_meter=meter)  # the paper's protocol, cached
    train, validation = paper.split()
    protocol = keyvision.RenderProtocol(runs=args.runs, validation_runs=0, angle_limit=args.angle)
    near = keyvision.render(args.scene, protocol=protocol, seed=args.seed, progress_meter=meter)
    parts = (train, near, validation)
    merged = keyvision.Frames(
        frames=np.concatenate([p.frames for p in parts]),
        u=np.concatenate([p.u for p in parts]),
        dt=paper.dt,
        extras={name: np.concatenate([p.extras[name] for p in parts]) for name in paper.extras},
        camera=paper.camera,
        info={
            **paper.info,
            "validation_runs": validation.num_runs,
            "upright_runs": {"runs": args.runs, "angle_limit": args.angle, "seed": args.seed,
                             "after_run": train.num_runs},
        },
    )
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = merged.save(out / "frames.npz")
    print(f"frames within {NEAR} rad of upright: paper's training runs {_near_share(train):.2%}, "
          f"the {args.runs} runs near upright {_near_share(near):.2%}")
    print(f"wrote {path}: {merged.num_runs} runs ({train.num_runs} + {near.num_runs} training, "
          f"{validation.num_runs} validation)")


if __name__ == "__main__":
    main()
