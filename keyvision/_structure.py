"""The constraints of any rendered planar scene on its keypoints, in the image frame: what KeyCLD's
dynamics need to learn a mechanism that is not one of the paper's three scenes."""

import jax
import jax.numpy as jnp
import numpy as np

import cldyn
from cldyn._constraint import AffineMap, BilinearConstraint, NormConstraint
from cldyn._misc import optional_import

from ._data import Frames

_AFFINE_TOL = 1e-9  # relative: a homography whose last row is (0, 0, c) to this is affine
_RIGID_TOL = 1e-4  # relative: the scene's constraint values along a run of true keypoints


def scene_constraint(frames: Frames) -> cldyn.AbstractConstraint:
    """The holonomic constraints of the frames' scene on its keypoints, in the image frame.

    `cldyn.mujoco.from_mjcf` reads the constraints of the scene's MJCF (`frames.info["mjcf_xml"]`)
    in the plane of motion, in metres; the camera's map (`frames.camera`) carries them to the image
    frame, in which keyvision's keypoints live. A pivot becomes the image point it is seen at
    (`cldyn.Anchor(i, point)`), a rod stays a rod (`cldyn.Distance`), a rail along a plane axis
    becomes a rail along the image axis it is seen along (`cldyn.FixedCoordinate`), a rail at an
    angle or keypoints tied to a body that does not turn (`cldyn.LinearConstraint`, `rows @ x`) keep
    their rows, and a slide on a turning body (`d(x) . n(x)`) or a hinge whose anchor is no keypoint
    (`|d(x)|`) their affine maps `d`, `n`, carried through the camera's map. For KeyCLD's scenes this is
    `cldyn.keycld_constraint` (the paper's figure 7); for any other planar chain of hinges and slides
    it is the same structure, read from the scene, so `keyvision train` can learn its dynamics from
    the frames without naming a constraint.

    The map must be a similarity (a camera that looks straight at the plane, as keyvision's scenes
    do): distances in the plane are then distances in the image. The constraints are checked on the
    frames' true keypoints (`frames.extras["keypoints"]`), which must keep them along every run.

    **Arguments:**

    - `frames`: rendered frames (`keyvision.render`), with their MJCF, camera and true keypoints.

    **Returns:** a `cldyn.AbstractConstraint` on the `2K` image-frame coordinates of the `K`
    keypoints (one constraint alone, or a `cldyn.Stack`). A scene whose keypoints the constraints do
    not hold on, or a camera map that is not a similarity raises a `ValueError` that says which.

    !!! example

        ```python
        frames = keyvision.Frames.load("data/frames.npz")     # frames of any planar MJCF
        constraint = keyvision.scene_constraint(frames)       # e.g. Stack([Anchor(0, (0.1, 0.2)), ...])
        model = cldyn.keycld_model(2 * len(frames.info["keypoint_names"]), frames.u.shape[-1],
                                   constraint, key=jax.random.key(0))
        ```
    """
    bridge, linear, offset, names = scene_bridge(frames, "scene_constraint")
    plane = bridge.system.constraint
    if plane is None:
        raise ValueError("scene_constraint: the scene has no constraints on its keypoints")
    parts = plane.constraints if isinstance(plane, cldyn.Stack) else (plane,)
    keypoints = frames.extras.get("keypoints")
    if keypoints is None:
        raise ValueError("scene_constraint: the frames carry no true keypoints (extras['keypoints'])")
    count = np.shape(keypoints)[-1] // 2
    mapped = [_to_image(part, linear, offset, frames.camera, count) for part in parts]
    _check_rigid(plane, parts, frames, names)
    return mapped[0] if len(mapped) == 1 else cldyn.Stack(mapped)


def scene_bridge(frames: Frames, caller: str) -> tuple:
    """`(from_mjcf's model of the frames' scene on their keypoints, A, b, keypoint names)`, with
    `plane = A @ image + b` the camera's map; errors name `caller`."""
    if not isinstance(frames, Frames):
        raise TypeError(f"{caller}: frames must be keyvision.Frames, got {type(frames).__name__}")
    xml = frames.info.get("mjcf_xml")
    if not xml:
        raise ValueError(f"{caller}: the frames carry no MJCF (frames.info['mjcf_xml']); render them again")
    mujoco = optional_import("cldyn.mujoco", purpose=f"keyvision.{caller}")
    linear, offset = _affine(frames.camera, caller)
    names = [str(name) for name in frames.info.get("keypoint_names", [])]
    # keypoints rendered at named sites (`keyvision.render(keypoints=)`) are the same sites for from_mjcf
    at_sites = bool(names) and set(names) <= set(_site_names(xml))
    try:
        bridge = mujoco.from_mjcf(xml, keypoints=names if at_sites else None)
    except ValueError as error:
        raise ValueError(f"{caller}: the scene on the frames' keypoints: {error}") from None
    if names and len(bridge.keypoint_names) != len(names):  # the same points are checked below
        chosen = ", ".join(bridge.keypoint_names)
        raise ValueError(
            f"{caller}: the scene's constraints are on the keypoints {chosen} (cldyn.mujoco."
            f"from_mjcf's choice: a turning body needs a keypoint of its own); the frames have "
            f"{', '.join(names)}. Render them at sites placed there (keyvision.render(keypoints=))"
        )
    return bridge, linear, offset, names


def _site_names(xml: str) -> list[str]:
    from cldyn.mujoco._scenes import load_model

    from ._scene import _mujoco

    mujoco = _mujoco()

    model = load_model(xml)[0]
    return [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_SITE, i) or "" for i in range(model.nsite)]


def _affine(camera, caller: str = "scene_constraint") -> tuple[np.ndarray, np.ndarray]:
    """`A` and `b` of plane = A @ image + b, checked to be a similarity."""
    h = np.asarray(camera.homography, dtype=float)
    if np.max(np.abs(h[2, :2])) > _AFFINE_TOL * abs(h[2, 2]):
        raise ValueError(
            f"{caller}: the camera sees the plane in perspective (its homography is not affine); "
            "distances in the plane are not distances in the image"
        )
    linear = h[:2, :2] / h[2, 2]
    gram = linear.T @ linear
    if not np.allclose(gram, gram[0, 0] * np.eye(2), rtol=0, atol=1e-9 * abs(gram[0, 0])):
        raise ValueError(
            f"{caller}: the camera stretches the plane unevenly (its map is not a similarity); "
            "distances in the plane are not distances in the image"
        )
    return linear, h[:2, 2] / h[2, 2]


def _to_image(part, linear: np.ndarray, offset: np.ndarray, camera, count: int) -> cldyn.AbstractConstraint:
    if isinstance(part, cldyn.Distance):
        return cldyn.Distance(part.first, part.second)
    if isinstance(part, cldyn.Anchor):
        point = camera.to_image(np.asarray(part.point, dtype=float))
        scale = float(np.max(np.abs(point))) + 1.0
        point = np.where(np.abs(point) < 1e-12 * scale, 0.0, point)  # the image centre, not 1e-17
        return cldyn.Anchor(part.keypoint, point)
    if isinstance(part, cldyn.FixedCoordinate):
        row = np.abs(linear[part.axis])  # the fixed plane coordinate in terms of the image coordinates
        seen = np.flatnonzero(row > 1e-9 * row.max())
        if len(seen) == 1:
            return cldyn.FixedCoordinate(part.keypoint, axis=int(seen[0]))
        # a rail along a plane axis that the camera sees at an angle to the image axes
        rows = np.zeros((1, 2 * count))
        rows[0, 2 * part.keypoint + part.axis] = 1.0
        part = cldyn.LinearConstraint(rows)
    if isinstance(part, cldyn.LinearConstraint):
        # rows @ x_plane with x_plane = (I kron A) x_image + b: the same rows times I kron A (the
        # constant is no part of a constraint, which keeps its initial value)
        return cldyn.LinearConstraint(_clean(_on(part.rows, count) @ np.kron(np.eye(count), linear)))
    if isinstance(part, BilinearConstraint | NormConstraint):
        # d(x_plane) = M x_plane + c = (M (I kron A)) x_image + (M (1 kron b) + c): still affine
        def through(form):
            matrix, const = _on(form.matrix, count), np.asarray(form.const, dtype=float)
            return AffineMap(
                jnp.asarray(_clean(matrix @ np.kron(np.eye(count), linear))),
                jnp.asarray(matrix @ np.tile(offset, count) + const),
            )

        if isinstance(part, NormConstraint):
            return NormConstraint(through(part.difference))
        return BilinearConstraint(through(part.displacement), through(part.normal))
    raise ValueError(
        f"scene_constraint: the scene has a constraint of kind {type(part).__name__}, which "
        "keyvision cannot carry to the image"
    )


def _on(matrix, count: int) -> np.ndarray:
    """A constraint's coefficients on the keypoints, checked to be on the frames' `count`."""
    matrix = np.asarray(matrix, dtype=float)
    if matrix.shape[1] != 2 * count:
        raise ValueError(
            f"scene_constraint: a constraint on {matrix.shape[1] // 2} keypoints; the frames have {count}"
        )
    return matrix


def _clean(matrix: np.ndarray) -> np.ndarray:
    """Entries below 1e-12 of their row's largest set to zero: what a map's rounding leaves in place of 0."""
    return np.where(np.abs(matrix) < 1e-12 * np.abs(matrix).max(axis=1, keepdims=True), 0.0, matrix)


def _forms(part) -> tuple:
    return (part.difference,) if isinstance(part, NormConstraint) else (part.displacement, part.normal)


def _keypoints_of(part) -> tuple[int, ...]:
    if isinstance(part, cldyn.Distance):
        return (part.first, part.second)
    if isinstance(part, cldyn.LinearConstraint | BilinearConstraint | NormConstraint):
        forms = [part.rows] if isinstance(part, cldyn.LinearConstraint) else [f.matrix for f in _forms(part)]
        used = np.any(np.concatenate([np.asarray(f) for f in forms]) != 0, axis=0)
        return tuple(sorted({int(i) // 2 for i in np.flatnonzero(used)}))
    return (part.keypoint,)


def _check_rigid(plane, parts, frames: Frames, names: list) -> None:
    """The scene's constraints are on the frames' keypoints and hold on them: constant along every run."""
    keypoints = frames.extras.get("keypoints")
    if keypoints is None:
        raise ValueError("scene_constraint: the frames carry no true keypoints (extras['keypoints'])")
    keypoints = np.asarray(keypoints, dtype=float)
    used = max(i for part in parts for i in _keypoints_of(part))
    if 2 * (used + 1) > keypoints.shape[-1]:
        raise ValueError(
            f"scene_constraint: the scene's constraints name keypoint {used}; the frames have "
            f"{keypoints.shape[-1] // 2} ({', '.join(names)})"
        )
    flat = keypoints.reshape(-1, keypoints.shape[-1])
    values = np.asarray(jax.vmap(plane)(jax.numpy.asarray(flat))).reshape(*keypoints.shape[:2], -1)
    spread = np.max(np.abs(values - values[:, :1]), axis=(0, 1))
    if np.any(spread > _RIGID_TOL * (np.max(np.abs(values)) + np.max(np.abs(flat)))):
        raise ValueError(
            "scene_constraint: the scene's constraints do not hold on the frames' keypoints "
            f"({', '.join(names)}): their values vary by up to {np.max(spread):.3g} along a run. "
            "Keypoints named by sites must be the points that the scene's joints tie together"
        )
