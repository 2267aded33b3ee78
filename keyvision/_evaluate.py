"""Diagnostics of learned keypoints against the ground truth rendered with the frames."""

import numpy as np
from jaxtyping import Float

from ._data import Frames


def pose_features(frames: Frames) -> Float[np.ndarray, "R T P"]:
    """The true pose as features that an affine map of good keypoints can reproduce: `sin` and `cos`
    of every hinge angle, and the position of every slide.

    **Arguments:**

    - `frames`: rendered `keyvision.Frames` (with `extras["qpos"]` and the joint types in `info`).

    **Returns:** `(R, T, P)` features, `P = 2 * hinges + slides`.

    !!! example

        ```python
        truth = keyvision.pose_features(frames)     # pendulum: (R, T, 2) = sin, cos of the angle
        ```
    """
    qpos = np.asarray(frames.extras["qpos"])
    columns = []
    for kind, index in zip(frames.info["joint_types"], frames.info["joint_qpos_index"]):
        if kind == "hinge":
            columns += [np.sin(qpos[..., index]), np.cos(qpos[..., index])]
        elif kind == "slide":
            columns.append(qpos[..., index])
        else:
            raise ValueError(f"pose_features: a {kind} joint has no planar pose feature")
    return np.stack(columns, axis=-1)


def keypoint_tracking(
    estimated: Float[np.ndarray, "N ..."],
    truth_pose: Float[np.ndarray, "N ... P"],
    *,
    fit_fraction: float = 0.5,
) -> float:
    """How well learned keypoints track the true pose: the held-out `R^2` of an affine map from the
    keypoints to the pose features.

    An affine map `truth ~ A @ keypoints + b` is fitted by least squares on the first
    `fit_fraction` of the leading axis (e.g. runs) and scored on the rest:

    $$R^2 = 1 - \\frac{\\sum \\lVert y - \\hat y \\rVert^2}{\\sum \\lVert y - \\bar y \\rVert^2}$$

    pooled over all features, with `\\bar y` the mean over the held-out rows. 1 means the keypoints
    determine the pose (up to an affine map: units, orientation and offset of the image frame are
    free); 0 means they explain no more than the mean pose. Keypoints that slide along a body, or
    settle on the background, score low even when the reconstruction looks right.

    **Arguments:**

    - `estimated`: keypoints, `(N, ..., K, 2)` or `(N, ..., 2K)`, e.g. `(R, T, K, 2)`.
    - `truth_pose`: the matching pose features `(N, ..., P)`, e.g. `keyvision.pose_features(frames)`.
    - `fit_fraction`: the fraction of the leading axis used to fit the map (the rest scores it).

    **Returns:** the held-out `R^2` (at most 1; negative if the map does worse than the mean).

    !!! example

        ```python
        keypoints = jax.vmap(jax.vmap(estimator))(frames.images())      # (R, T, K, 2)
        keyvision.keypoint_tracking(keypoints, keyvision.pose_features(frames))
        ```
    """
    estimated = np.asarray(estimated, dtype=float)
    truth = np.asarray(truth_pose, dtype=float)
    leading = truth.shape[:-1]
    if estimated.shape[: len(leading)] != leading:
        raise ValueError(
            f"keypoint_tracking: estimated {estimated.shape} and truth_pose {truth.shape} disagree in "
            f"their leading axes {leading}"
        )
    if not 0 < fit_fraction < 1:
        raise ValueError(f"keypoint_tracking: fit_fraction must lie in (0, 1), got {fit_fraction}")
    cut = int(round(fit_fraction * leading[0]))
    if not 0 < cut < leading[0]:
        raise ValueError(f"keypoint_tracking: {leading[0]} rows cannot be split at fraction {fit_fraction}")
    inputs = estimated.reshape(*leading, -1)
    design = np.concatenate([inputs, np.ones((*leading, 1))], axis=-1)
    fit_x, test_x = design[:cut].reshape(-1, design.shape[-1]), design[cut:].reshape(-1, design.shape[-1])
    fit_y, test_y = truth[:cut].reshape(-1, truth.shape[-1]), truth[cut:].reshape(-1, truth.shape[-1])
    coefficients, *_ = np.linalg.lstsq(fit_x, fit_y, rcond=None)
    residual = np.sum((test_x @ coefficients - test_y) ** 2)
    spread = np.sum((test_y - test_y.mean(axis=0)) ** 2)
    return float(1 - residual / spread)
