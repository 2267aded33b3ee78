"""KeyCLD's learnable models (appendix A.4), the constraint structure of its three scenes, and the
models of its ablation built from a JSON specification (what a fit directory records)."""

from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
from jaxtyping import PRNGKeyArray

from ._baselines import SecondOrderNeuralODE
from ._constraint import (
    AbstractConstraint,
    AffineMap,
    Anchor,
    BilinearConstraint,
    Distance,
    FixedCoordinate,
    LinearConstraint,
    NormConstraint,
    Stack,
)
from ._coordinates import AbstractCoordinate, HingeAngle, SliderPosition
from ._custom_types import ArrayInput
from ._input import JointInput, MLPInput
from ._mass import CoupledMasses, PointMasses
from ._misc import check_positive
from ._potential import Gravity, MLPPotential
from ._system import ConstrainedLagrangian

KEYCLD_SCENES = ("pendulum", "cartpole", "acrobot")
"""The three scenes of the KeyCLD paper, in the order of its tables."""


def keycld_model(
    size: int,
    num_inputs: int,
    constraint: AbstractConstraint | None,
    *,
    key: PRNGKeyArray,
    masses: ArrayInput | None = None,
    width: int = 32,
    depth: int = 2,
    dim: int = 2,
    mass: str = "point",
    potential: str = "mlp",
    joints: Sequence[AbstractCoordinate] | None = None,
) -> ConstrainedLagrangian:
    """The learnable KeyCLD model: point masses (eq. 14), an MLP potential and an MLP input matrix.

    Appendix A.4 of the paper: `V(x)` and `g(x)` are CELU MLPs with two hidden layers of 32 units,
    the masses are learned through their square roots. With `constraint=None` this is the KeyCLD-NC
    ablation.

    `mass="coupled"`, `potential="gravity"` and `joints` replace the networks by the structure of
    rigid bodies in uniform gravity driven by joint motors, each exact wherever every body carries
    two of the keypoints (or one and a fixed pivot): the kinetic energy is then a constant quadratic
    form in the keypoint velocities (`CoupledMasses`, when the centres of mass lie on the lines
    between keypoints); the height of every centre of mass is a linear function of the keypoints, so
    the potential is linear (`Gravity` with learnable weights on every coordinate, which also learns
    the direction of gravity in the image); and a motor's torque on a joint does the virtual work
    `u gear dq(x)` (`JointInput`, learnable gears). Being exact where the data is sparse (an
    acrobot learnt from images is hardly ever near upright), they extrapolate where the networks do
    not.

    **Arguments:**

    - `size`: the number `k` of keypoint coordinates (`dim` per keypoint).
    - `num_inputs`: the number `l` of controls (0 for none: no input matrix).
    - `constraint`: the holonomic constraints, e.g. `cldyn.Anchor(0)` for the pendulum, or `None`.
    - `key`: a `jax.random` key.
    - `masses`: the initial keypoint masses, shape `(size / dim,)`; ones by default.
    - `width`, `depth`: of both MLPs.
    - `dim`: dimension of each keypoint.
    - `mass`: `"point"` for KeyCLD's diagonal point masses (eq. 14), or `"coupled"` for a constant
      mass matrix `A \\otimes I_d` that couples keypoints (`CoupledMasses`), exact for rigid bodies
      whose centre of mass lies between their keypoints.
    - `potential`: `"mlp"` (KeyCLD's), or `"gravity"` for the linear potential `cldyn.Gravity`
      (its weights start at zero).
    - `joints`: the joint coordinate driven by each control (`cldyn.keycld_joints` for KeyCLD's
      scenes): the input matrix is `cldyn.JointInput(joints)` (gears start at one) instead of an MLP.

    **Returns:** a `ConstrainedLagrangian`.

    !!! example

        ```python
        constraint = cldyn.Stack([cldyn.FixedCoordinate(0, axis=1), cldyn.Distance(0, 1)])
        cartpole = cldyn.keycld_model(4, 2, constraint, key=jax.random.key(0))
        nc = cldyn.keycld_model(4, 2, None, key=jax.random.key(0))   # KeyCLD-NC
        structured = cldyn.keycld_model(4, 2, constraint, key=jax.random.key(0), mass="coupled",
                                        potential="gravity", joints=cldyn.keycld_joints("cartpole"))
        ```
    """
    if size <= 0 or size % dim:
        raise ValueError(f"size must be a positive multiple of dim={dim}, got {size}")
    if constraint is not None and not isinstance(constraint, AbstractConstraint):
        raise TypeError(f"constraint must be an AbstractConstraint or None, got {type(constraint).__name__}")
    count = size // dim
    if constraint is not None:
        try:  # a constraint on keypoints the coordinates lack fails only when traced: say so here
            jax.eval_shape(constraint, jax.ShapeDtypeStruct((size,), jnp.float32))
        except (TypeError, IndexError, ValueError) as error:
            raise ValueError(
                f"the constraint does not apply to {count} keypoint{'s' if count > 1 else ''} of dimension "
                f"{dim} (size {size}): {error}"
            ) from None
    masses = jnp.ones(count) if masses is None else jnp.asarray(masses, dtype=float)
    if masses.shape != (count,):
        raise ValueError(f"masses must have shape ({count},), one per keypoint; got {masses.shape}")
    if mass not in ("point", "coupled"):
        raise ValueError(f"mass must be 'point' or 'coupled', got {mass!r}")
    if potential not in ("mlp", "gravity"):
        raise ValueError(f"potential must be 'mlp' or 'gravity', got {potential!r}")
    if joints is not None:
        joints = tuple(joints)
        if len(joints) != num_inputs:
            raise ValueError(f"joints: one joint per control, got {len(joints)} for num_inputs={num_inputs}")
        if dim != 2:
            raise ValueError(f"joints: joint coordinates are planar (dim=2), got dim={dim}")
        for joint in joints:
            try:
                jax.eval_shape(joint, jax.ShapeDtypeStruct((size,), jnp.float32))
            except (TypeError, IndexError, ValueError) as error:
                raise ValueError(f"joints: {joint!r} does not apply to {count} keypoints: {error}") from None
    potential_key, input_key = jax.random.split(key)
    if num_inputs == 0:
        input_matrix = None
    elif joints is not None:
        input_matrix = JointInput(joints)
    else:
        input_matrix = MLPInput(size, num_inputs, width=width, depth=depth, key=input_key)
    return ConstrainedLagrangian(
        mass=PointMasses(masses, dim=dim) if mass == "point" else CoupledMasses(masses, dim=dim),
        potential=MLPPotential(size, width=width, depth=depth, key=potential_key)
        if potential == "mlp"
        else Gravity(jnp.zeros(size, dtype=masses.dtype)),
        constraint=constraint,
        input_matrix=input_matrix,
    )


def keycld_joints(system: str) -> tuple[AbstractCoordinate, ...]:
    """The joints that the controls of KeyCLD's scenes drive, in the keypoints of `keycld_constraint`.

    - `"pendulum"`: the hinge, `HingeAngle(child=(None, 0))`;
    - `"cartpole"`: the cart's slide `SliderPosition(0)` and the pole's hinge `HingeAngle(child=(0, 1))`;
    - `"acrobot"`: the shoulder `HingeAngle(child=(None, 0))` and the elbow
      `HingeAngle(child=(0, 1), parent=(None, 0))`.

    One per control, in the order of the scenes' actuators; with a fixed pivot at the origin (where
    `keycld_constraint` puts it). Directions and gears are left to learn (`cldyn.JointInput`), so
    the image's orientation does not matter.

    !!! example

        ```python
        g = cldyn.JointInput(cldyn.keycld_joints("acrobot"))   # shoulder and elbow motors
        ```
    """
    key = system.removeprefix("keycld/")
    if key == "pendulum":
        return (HingeAngle(child=(None, 0)),)
    if key == "cartpole":
        return (SliderPosition(0), HingeAngle(child=(0, 1)))
    if key == "acrobot":
        return (HingeAngle(child=(None, 0)), HingeAngle(child=(0, 1), parent=(None, 0)))
    raise ValueError(f"unknown KeyCLD system {system!r}; choose one of {', '.join(KEYCLD_SCENES)}")


def keycld_constraint(system: str) -> AbstractConstraint:
    """The constraints of KeyCLD's models (paper figure 7), with the pivot at the origin.

    - `"pendulum"`: `Anchor(0)`, the tip at a fixed distance from the pivot;
    - `"cartpole"`: `FixedCoordinate(0, axis=1)` (the cart keeps its height) and `Distance(0, 1)`
      (cart to pole tip);
    - `"acrobot"`: `Anchor(0)` (the elbow) and `Distance(0, 1)` (elbow to tip).

    Only the Jacobians enter the dynamics (eq. 6), so the lengths need not be known.

    !!! example

        ```python
        model = cldyn.keycld_model(4, 2, cldyn.keycld_constraint("acrobot"), key=jax.random.key(0))
        ```
    """
    key = system.removeprefix("keycld/")
    if key == "pendulum":
        return Anchor(0)
    if key == "cartpole":
        return Stack([FixedCoordinate(0, axis=1), Distance(0, 1)])
    if key == "acrobot":
        return Stack([Anchor(0), Distance(0, 1)])
    raise ValueError(f"unknown KeyCLD system {system!r}; choose one of {', '.join(KEYCLD_SCENES)}")


def constraint_entries(constraint: AbstractConstraint) -> list[dict]:
    """A planar constraint of pivots, rods, rails, linear ties and the affine forms that `from_mjcf`
    reads (a slide on a turning body, a hinge whose anchor is no keypoint) as JSON entries
    (`model_from_spec`'s list form)."""
    parts = constraint.constraints if isinstance(constraint, Stack) else (constraint,)
    entries = []
    for part in parts:
        if getattr(part, "dim", 2) != 2:
            raise ValueError(f"constraint entries are planar (dim=2); got {part!r}")
        if isinstance(part, Anchor):
            entries.append({"anchor": part.keypoint, "point": [float(v) for v in part.point]})
        elif isinstance(part, Distance):
            entries.append({"distance": [part.first, part.second]})
        elif isinstance(part, FixedCoordinate):
            entries.append({"fixed": part.keypoint, "axis": part.axis})
        elif isinstance(part, LinearConstraint):
            entries.append({"linear": [[float(v) for v in row] for row in part.rows]})
        elif isinstance(part, BilinearConstraint):
            entries.append(
                {
                    "bilinear": {
                        "displacement": _map_entry(part.displacement),
                        "normal": _map_entry(part.normal),
                    }
                }
            )
        elif isinstance(part, NormConstraint):
            entries.append({"norm": _map_entry(part.difference)})
        else:
            raise ValueError(f"no JSON entry for a {type(part).__name__} constraint")
    return entries


def _map_entry(affine: AffineMap) -> dict:
    return {
        "matrix": [[float(v) for v in row] for row in affine.matrix],
        "const": [float(v) for v in affine.const],
    }


def _map_from(entry: dict) -> AffineMap:
    matrix, const = jnp.asarray(entry["matrix"], dtype=float), jnp.asarray(entry["const"], dtype=float)
    if matrix.ndim != 2 or matrix.shape[0] != 2 or const.shape != (2,):
        raise ValueError(
            f"an affine map is a (2, k) matrix and a (2,) const; got {matrix.shape}, {const.shape}"
        )
    return AffineMap(matrix, const)


_ENTRY_KINDS = ("anchor", "distance", "fixed", "linear", "bilinear", "norm")


def _from_entries(entries: list) -> AbstractConstraint:
    parts: list[AbstractConstraint] = []
    for entry in entries:
        if not isinstance(entry, dict) or len(set(entry) & set(_ENTRY_KINDS)) != 1:
            raise ValueError(
                f"model spec: a constraint entry is one of {', '.join(_ENTRY_KINDS)}; got {entry!r}"
            )
        try:
            if "anchor" in entry:
                parts.append(Anchor(int(entry["anchor"]), entry.get("point")))
            elif "distance" in entry:
                first, second = entry["distance"]
                parts.append(Distance(int(first), int(second)))
            elif "linear" in entry:
                parts.append(LinearConstraint(entry["linear"]))
            elif "bilinear" in entry:
                forms = entry["bilinear"]
                parts.append(BilinearConstraint(_map_from(forms["displacement"]), _map_from(forms["normal"])))
            elif "norm" in entry:
                parts.append(NormConstraint(_map_from(entry["norm"])))
            else:
                parts.append(FixedCoordinate(int(entry["fixed"]), axis=int(entry["axis"])))
        except (KeyError, TypeError, ValueError) as error:
            raise ValueError(f"model spec: constraint entry {entry!r}: {error}") from None
    if not parts:
        raise ValueError("model spec: an empty list of constraints")
    return parts[0] if len(parts) == 1 else Stack(parts)


def _keycld(spec: dict, key, mass: str, structured: bool = False):
    scene = spec.get("constraint")
    if isinstance(scene, list) and not structured:
        constraint = _from_entries(scene)
    else:
        scene = scene.removeprefix("keycld/") if isinstance(scene, str) else scene
        if scene not in KEYCLD_SCENES:
            raise ValueError(
                f"model spec: {spec['kind']!r} needs a constraint, one of {', '.join(KEYCLD_SCENES)}"
                + ("" if structured else " or a list of constraint entries")
                + f"; got {scene!r}"
            )
        constraint = keycld_constraint(scene)
    return keycld_model(
        spec["size"],
        spec["num_inputs"],
        constraint,
        key=key,
        width=spec["width"],
        depth=spec["depth"],
        mass=mass,
        potential="gravity" if structured else "mlp",
        joints=keycld_joints(scene) if structured and spec["num_inputs"] else None,
    )


def _nc(spec: dict, key):
    return keycld_model(
        spec["size"], spec["num_inputs"], None, key=key, width=spec["width"], depth=spec["depth"]
    )


def _node2(spec: dict, key):
    return SecondOrderNeuralODE(
        spec["size"], spec["num_inputs"], width=spec["width"], depth=spec["depth"], key=key
    )


# The builders of the model kinds a fit directory can name; a spec is JSON, so its kind is a string.
_BUILDERS: dict[str, Callable] = {
    "keycld": lambda spec, key: _keycld(spec, key, "point"),
    "keycld-coupled": lambda spec, key: _keycld(spec, key, "coupled"),
    "keycld-structured": lambda spec, key: _keycld(spec, key, "coupled", structured=True),
    "nc": _nc,
    "node2": _node2,
}
MODEL_KINDS = tuple(_BUILDERS)


def model_from_spec(spec: dict, *, key: PRNGKeyArray):
    """The untrained model that a specification describes (the `model` entry of a fit's `fit.json`).

    **Arguments:**

    - `spec`: a dict with `kind` (`"keycld"`, `"keycld-coupled"` (coupled masses),
      `"keycld-structured"` (coupled masses, `Gravity` and the scene's `keycld_joints`: no
      networks), `"nc"` (KeyCLD without constraints) or `"node2"` (`SecondOrderNeuralODE`)),
      `size` (`k`), `num_inputs` (`l`), `width` and `depth` of the networks, and for the KeyCLD
      kinds `constraint`, a scene of `cldyn.KEYCLD_SCENES`, or (but for `"keycld-structured"`,
      whose joints are the scene's) a list of JSON entries, one per constraint:
      `{"anchor": i, "point": [x, y]}` (`Anchor`), `{"distance": [i, j]}` (`Distance`) and
      `{"fixed": i, "axis": a}` (`FixedCoordinate`), `{"linear": [[...], ...]}` (`LinearConstraint`,
      its rows), and the forms of affine maps `d(x) = matrix @ x + const` that `cldyn.mujoco.from_mjcf`
      reads, `{"bilinear": {"displacement": d, "normal": n}}` (`d(x) . n(x)`: a slide on a turning
      body) and `{"norm": d}` (`|d(x)|`: a hinge whose anchor is no keypoint), each map
      `{"matrix": [[...], [...]], "const": [c0, c1]}`; as `keyvision train` writes for a scene
      that is not one of KeyCLD's (`keyvision.scene_constraint`).
    - `key`: a `jax.random` key for the initial parameters.

    **Returns:** the model. A spec that lacks an entry or names an unknown kind or scene raises a
    `ValueError` that says which.

    !!! example

        ```python
        spec = {"kind": "keycld", "size": 4, "num_inputs": 2, "width": 32, "depth": 2,
                "constraint": "acrobot"}
        model = cldyn.model_from_spec(spec, key=jax.random.key(0))
        spec["constraint"] = [{"anchor": 0, "point": [0.0, 0.5]}, {"distance": [0, 1]}]
        chain = cldyn.model_from_spec(spec, key=jax.random.key(0))   # pivot at (0, 0.5)
        ```
    """
    if not isinstance(spec, dict):
        raise ValueError(f"model spec must be a dict, got {type(spec).__name__}")
    builder = _BUILDERS.get(spec.get("kind"))
    if builder is None:
        raise ValueError(
            f"model spec: unknown kind {spec.get('kind')!r}; choose one of {', '.join(MODEL_KINDS)}"
        )
    spec = dict(spec)
    for name, allow_zero in (("size", False), ("num_inputs", True), ("width", False), ("depth", True)):
        if name not in spec:
            raise ValueError(f"model spec: missing {name!r}")
        spec[name] = check_positive(f"model spec: {name}", spec[name], integer=True, allow_zero=allow_zero)
    return builder(spec, key)
