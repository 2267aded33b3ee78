"""The energy balance beside `keyvision.identify`: its entries in MuJoCo's units, and its damping added
to the learnt model only where it passes `cldyn.identify`'s held-out rollout test."""

import jax.numpy as jnp

import cldyn
from cldyn._identify.base import add_dissipation
from cldyn._identify.errors import held_out_rollout_rmse


def balance_entry(found, j: int, structure, convert) -> dict:
    """Joint `j` of a `cldyn.EnergyBalance`, in the model's units and converted by
    `convert(where, kind, value)` as a detected damping."""
    where = found.joint_names[j]
    kind = structure.kinds[structure.names.index(where)]
    return {
        "where": where,
        "value": convert(where, kind, float(found.damping[j])),
        "ci": tuple(convert(where, kind, float(c)) for c in found.interval[j]),
        "value_model": float(found.damping[j]),
        "ci_model": tuple(float(c) for c in found.interval[j]),
        "detected": where in found.detected,
    }


def add_checked_balance(dynamics, balanced, effects, structure, data, held_out_runs, smoothing=None):
    """The balance's damping at each joint where its interval lies above zero and no damping was
    detected, added to `dynamics` where it lowers the held-out rollout error as `cldyn.identify`
    requires of its own detections: each addition against the others alone, then all of them against
    none.

    **Arguments:** `dynamics`, the model after `cldyn.identify`; `balanced`, `balance_entry`s;
    `effects`, the detections as `keyvision.identify` lists them; `structure`, the `JointStructure`;
    `data`, the `cldyn.Sequences` identified; `held_out_runs`, identify's held-out runs of `data`;
    `smoothing`, the `cldyn.Smoothing` identify ran with (its default if `None`).

    **Returns:** `(dynamics, added, notes)`: the model with the damping that passed, the effect entries
    of that damping (`"source": "energy balance"`), and a note for each joint that did not pass.
    """
    damped = {e["where"] for e in effects if e["name"] == "joint_damping"}
    wanted = [b for b in balanced if b["detected"] and b["where"] not in damped]
    if not wanted:
        return dynamics, [], []

    def with_(entries):
        if not entries:
            return dynamics
        coordinates = [structure.coordinates[b["where"]] for b in entries]
        damping = jnp.asarray([b["value_model"] for b in entries], dtype=jnp.float64)
        return add_dissipation(dynamics, cldyn.JointDamping(coordinates, damping))

    options = {} if smoothing is None else {"smoothing": smoothing}

    def rmse(*trials):
        return held_out_rollout_rmse(
            [with_(t) for t in trials],
            data,
            held_out_runs,
            coordinates=tuple(structure.coordinates.values()),
            joints=structure.joint_map,
            **options,
        )

    alone = [[o for o in wanted if o is not b] for b in wanted] if len(wanted) > 1 else []
    full, *without, none = rmse(wanted, *alone, [])
    notes, kept = [], list(wanted)
    for b, error in zip(wanted, without):
        if not full < error:
            kept.remove(b)
            notes.append(
                f"the energy balance's joint_damping[{b['where']}] does not lower the held-out rollout error "
                f"({error:.4g} without it, {full:.4g} with it, in the keypoints' units): not added"
            )
    if kept and len(kept) < len(wanted):
        (full,) = rmse(kept)
    if kept and not full < none:
        labels = ", ".join(f"joint_damping[{b['where']}]" for b in kept)
        notes.append(
            f"with the energy balance's {labels} the held-out rollout error does not drop ({none:.4g} -> "
            f"{full:.4g}, in the keypoints' units): not added"
        )
        kept = []
    added = [{"name": "joint_damping", **b, "source": "energy balance"} for b in kept]
    return with_(kept), added, notes
