"""The models fitted by `benchmarks/learning.py`, for the control benchmark: loading and overall scale."""

import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp

MODELS = pathlib.Path(__file__).resolve().parent / "results" / "learning"


def load(scene: str, name: str):
    """`(model, origin)` of the fitted `name` model of a KeyCLD scene in float64, or `None` if absent.

    `origin` is the point the model's keypoints are relative to (`cldyn.mujoco.keycld_origin`).
    """
    import cldyn
    import cldyn.mujoco as cm

    directory = MODELS / f"{scene}-{name}"
    if not (directory / "model.eqx").exists():
        return None
    model, _ = cldyn.load_fit(directory)
    model = jax.tree.map(lambda a: a.astype(jnp.float64) if eqx.is_inexact_array(a) else a, model)
    return model, [float(v) for v in cm.keycld_origin(scene)]


def scale(model, bridge) -> float:
    """The learned model's overall factor `a`: mass, potential and input matrix are learned only up to a
    common factor, measured here as the ratio of the mass matrices on the hanging state's tangent space.
    With keypoint damping, `EnergyShaping` on the model acts with the effective gains `kp / a`, `kd / a`.
    """
    hanging = bridge.joints.keypoints(jnp.zeros(len(bridge.joint_names)))
    jac = bridge.system.constraint.jacobian(hanging)
    tangent = jnp.eye(jac.shape[1]) - jnp.linalg.pinv(jac) @ jac
    learned = jnp.trace(tangent @ model.mass.matrix() @ tangent)
    return float(learned / jnp.trace(tangent @ bridge.system.mass.matrix() @ tangent))
