"""The class of MuJoCo models `from_mjcf` is exact for: checks that name the element outside it."""

import mujoco

from ._tree import Tree, body_name, joint_name, name_of

INCLUDABLE = ("damping", "stiffness", "armature")


def check_supported(model: mujoco.MjModel, tree: Tree) -> None:
    if model.ntendon:
        name = name_of(model, mujoco.mjtObj.mjOBJ_TENDON, 0, "tendon")
        raise ValueError(f"tendon {name!r}: tendons are not supported by from_mjcf")
    if model.neq and not model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_EQUALITY:
        name = name_of(model, mujoco.mjtObj.mjOBJ_EQUALITY, 0, "equality")
        raise ValueError(f"equality constraint {name!r}: equality constraints are not supported by from_mjcf")
    if getattr(model, "nflex", 0):
        raise ValueError("flex elements (deformable bodies) are not supported by from_mjcf")
    for g in tree.moving:
        joints = tree.joints[g]
        if len(joints) > 1:
            names = [joint_name(model, j) for j in joints]
            raise ValueError(
                f"body {body_name(model, g)!r} has {len(joints)} joints {names}; from_mjcf supports one "
                "hinge or slide per body (nest bodies to chain joints)"
            )
    for b in range(1, model.nbody):
        if model.body_gravcomp[b] != 0:
            raise ValueError(f"body {body_name(model, b)!r} has gravcomp, which from_mjcf does not model")
    if model.opt.density > 0 or model.opt.viscosity > 0:
        raise ValueError("fluid forces (option density/viscosity) are not modelled by from_mjcf")
    _check_contacts(model, tree)
    _check_actuators(model)


def _check_contacts(model: mujoco.MjModel, tree: Tree) -> None:
    flags = model.opt.disableflags
    if flags & (mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT):
        return
    filter_parent = not flags & mujoco.mjtDisableBit.mjDSBL_FILTERPARENT
    excluded = set(int(s) for s in model.exclude_signature)

    def collide(g1, g2, b1, b2):
        if g1 == g2 or g1 == 0 or g2 == 0:
            return False
        if filter_parent and (tree.parent[g1] == g2 or tree.parent[g2] == g1):
            return False
        return ((min(b1, b2) << 16) + max(b1, b2)) not in excluded

    for i in range(model.npair):
        a, b = int(model.pair_geom1[i]), int(model.pair_geom2[i])
        ba, bb = int(model.geom_bodyid[a]), int(model.geom_bodyid[b])
        if tree.group[ba] and tree.group[bb] and tree.group[ba] != tree.group[bb]:
            raise ValueError(
                f"contact pair {_geom(model, a)!r}-{_geom(model, b)!r} between moving bodies "
                "is not supported by from_mjcf"
            )
    geoms = range(model.ngeom)
    for a in geoms:
        for b in range(a + 1, model.ngeom):
            ba, bb = int(model.geom_bodyid[a]), int(model.geom_bodyid[b])
            if not collide(int(tree.group[ba]), int(tree.group[bb]), ba, bb):
                continue
            if (model.geom_contype[a] & model.geom_conaffinity[b]) or (
                model.geom_contype[b] & model.geom_conaffinity[a]
            ):
                raise ValueError(
                    f"geoms {_geom(model, a)!r} and {_geom(model, b)!r} on moving bodies "
                    f"{body_name(model, ba)!r} and {body_name(model, bb)!r} can collide; from_mjcf does "
                    "not model contacts (disable contact, or set contype/conaffinity)"
                )


def _geom(model, g: int) -> str:
    return name_of(model, mujoco.mjtObj.mjOBJ_GEOM, g, "geom")


def actuator_name(model, a: int) -> str:
    return name_of(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a, "actuator")


def _check_actuators(model: mujoco.MjModel) -> None:
    for a in range(model.nu):
        trn = mujoco.mjtTrn(int(model.actuator_trntype[a]))
        if trn != mujoco.mjtTrn.mjTRN_JOINT:
            raise ValueError(
                f"actuator {actuator_name(model, a)!r} uses a {trn.name} transmission; from_mjcf supports "
                "motors on hinge and slide joints"
            )
        dyn = mujoco.mjtDyn(int(model.actuator_dyntype[a]))
        gain = mujoco.mjtGain(int(model.actuator_gaintype[a]))
        bias = mujoco.mjtBias(int(model.actuator_biastype[a]))
        kind = _actuator_kind(dyn, gain, bias)
        if kind is not None:
            raise ValueError(
                f"actuator {actuator_name(model, a)!r} is {kind} (dynamics "
                f"{dyn.name.removeprefix('mjDYN_')}, gain {gain.name.removeprefix('mjGAIN_')}, bias "
                f"{bias.name.removeprefix('mjBIAS_')}): its "
                "force depends on the state or an activation, not on the control alone; from_mjcf supports "
                "<motor> actuators (and <general> ones with fixed gain, no bias and no dynamics)"
            )


def _actuator_kind(dyn, gain, bias) -> str | None:
    """What MJCF element an unsupported actuator most likely is, or `None` for a motor."""
    if (
        dyn == mujoco.mjtDyn.mjDYN_NONE
        and gain == mujoco.mjtGain.mjGAIN_FIXED
        and bias == mujoco.mjtBias.mjBIAS_NONE
    ):
        return None
    if dyn == mujoco.mjtDyn.mjDYN_INTEGRATOR:
        return "an <intvelocity> actuator (or a <general> one with an integrator)"
    if dyn != mujoco.mjtDyn.mjDYN_NONE:
        return "an actuator with activation dynamics (a <cylinder>, <muscle> or filtered <general>)"
    if gain == mujoco.mjtGain.mjGAIN_MUSCLE or bias == mujoco.mjtBias.mjBIAS_MUSCLE:
        return "a <muscle>"
    if bias == mujoco.mjtBias.mjBIAS_AFFINE:
        return "a servo (<position>, <velocity> or <damper>)"
    return "not a motor"


def check_include(include) -> tuple[str, ...]:
    if isinstance(include, str):
        include = (include,)
    include = tuple(include)
    for name in include:
        if name == "frictionloss":
            raise ValueError(
                "include: frictionloss is dry friction, a constraint in MuJoCo, not a smooth force, so "
                "it cannot be included exactly; cldyn.JointCoulomb approximates it. Allowed: "
                f"{', '.join(INCLUDABLE)}"
            )
        if name not in INCLUDABLE:
            raise ValueError(f"include: unknown effect {name!r}; allowed: {', '.join(INCLUDABLE)}")
    return include
