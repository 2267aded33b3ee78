"""How `fit` runs the optimiser steps between two log, validation or checkpoint points.

Both loops take the same steps with the same batches and the same guard against non-finite values:
a step whose loss or gradient is not finite changes nothing, and the chunk ends with the state before
it. They differ in what XLA compiles. `CompiledLoop` compiles the whole chunk as one `lax.while_loop`;
`HostLoop` compiles one step and dispatches it from Python, asynchronously, so the host still waits
for the device only once per chunk. XLA's CPU backend runs convolutions inside a compiled loop six to
eight times slower than the same convolutions outside one (`benchmarks/results/fit_loop.json`), so
networks of images train faster with `HostLoop` there, while small models gain from the compiled loop.
"""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp


def optax_promotion():
    """optax mixes Python floats with integer step counts (Adam's `decay**count`), which JAX's strict
    dtype promotion refuses; the optimiser alone is traced with the standard rules."""
    return jax.numpy_dtype_promotion("standard")


def _all_finite(tree):
    leaves = [jnp.all(jnp.isfinite(a)) for a in jax.tree.leaves(eqx.filter(tree, eqx.is_inexact_array))]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.array(True)


def _step(params, opt_state, static, data, key, index, *, loss, optimizer, batching, sharding):
    """One guarded optimiser step: `(new params, new opt_state, loss value, finite)`; the new state is
    the old one where the step is not finite."""

    def objective(p, batch):
        return loss(eqx.combine(p, static), batch)

    batch = batching.draw(data, jax.random.fold_in(key, index))
    if sharding is not None:
        batch = jax.lax.with_sharding_constraint(batch, sharding)
    value, grads = eqx.filter_value_and_grad(objective)(params, batch)
    with optax_promotion():
        updates, new_opt_state = optimizer.update(grads, opt_state, params)
    new_params = eqx.apply_updates(params, updates)
    finite = jnp.isfinite(value) & _all_finite(grads)

    # one conditional for the whole state, not a select per leaf: XLA copied the reduction of the
    # finiteness flags into every leaf's select (an autoencoder's step: 31,500 lines of optimised HLO
    # with selects, 17,900 with the conditional, compiled a sixth sooner; benchmarks/fit_loop.py ran
    # as fast or faster, 2026-11-27)
    def keep(new, old):
        return jax.lax.cond(finite, lambda: new, lambda: old)

    return keep(new_params, params), keep(new_opt_state, opt_state), value, finite


class AbstractStepLoop(eqx.Module):
    """How `fit` runs up to `count` optimiser steps from step `start`, stopping before the first
    non-finite one.

    `run` returns `(params, opt_state, losses, done, bad)`: the state after the `done` good steps,
    their losses in `losses[:done]` and, when `bad`, the failed step's loss in `losses[done]`.
    """

    @abc.abstractmethod
    def run(self, params, opt_state, static, data, key, start: int, count: int, *, loss, optimizer,
            batching, length: int, sharding):
        """The steps `start .. start + count - 1` (see the class docstring); no chunk of the fit is
        longer than `length`."""


@eqx.filter_jit
def _compiled_chunk(
    params, opt_state, static, data, key, start, count, *, loss, optimizer, batching, length, sharding
):
    dtype = jax.eval_shape(
        lambda p: loss(eqx.combine(p, static), batching.draw(data, key)), params
    ).dtype
    losses = jnp.full((length,), jnp.nan, dtype)

    def body(carry):
        i, params, opt_state, losses, _ = carry
        params, opt_state, value, finite = _step(
            params, opt_state, static, data, key, start + i,
            loss=loss, optimizer=optimizer, batching=batching, sharding=sharding,
        )
        return i + finite.astype(i.dtype), params, opt_state, losses.at[i].set(value), ~finite

    def more(carry):
        i, *_, bad = carry
        return (i < count) & ~bad

    i = jnp.zeros((), count.dtype)
    i, params, opt_state, losses, bad = jax.lax.while_loop(
        more, body, (i, params, opt_state, losses, jnp.array(False))
    )
    return params, opt_state, losses, i, bad


class CompiledLoop(AbstractStepLoop):
    """The steps of a chunk as one compiled `lax.while_loop` (`fit`'s default): no Python between
    steps, the fastest loop for small models. It is compiled once per model structure, loss,
    batching, optimiser (see `fit`) and chunk length (the shortest of `fit`'s intervals between log,
    validation and checkpoint points).

    !!! example

        ```python
        cldyn.fit(model, data, loss=cldyn.Collocation(), steps=2000, key=key, loop=cldyn.CompiledLoop())
        ```
    """

    def run(self, params, opt_state, static, data, key, start, count, *, loss, optimizer, batching,
            length, sharding):
        """See `AbstractStepLoop`."""
        return _compiled_chunk(
            params, opt_state, static, data, key, jnp.asarray(start), jnp.asarray(count),
            loss=loss, optimizer=optimizer, batching=batching, length=length, sharding=sharding,
        )


@eqx.filter_jit
def _host_step(params, opt_state, static, data, key, index, bad, done, *, loss, optimizer, batching,
               sharding):
    new_params, new_opt_state, value, finite = _step(
        params, opt_state, static, data, key, index,
        loss=loss, optimizer=optimizer, batching=batching, sharding=sharding,
    )
    go = finite & ~bad  # after a failed step the rest of the chunk changes nothing

    def keep(new, old):
        return jax.lax.cond(go, lambda: new, lambda: old)

    return (
        keep(new_params, params), keep(new_opt_state, opt_state), value, bad | ~finite,
        done + go.astype(done.dtype),
    )


class HostLoop(AbstractStepLoop):
    """One compiled step at a time, dispatched from Python without waiting for the device: the host
    reads the results once per chunk, as with `CompiledLoop`, and the steps and batches are the
    same. Use it for convolutional networks on CPU, where XLA runs a convolution inside a compiled
    loop about ten times slower than outside one (keyvision trains this way).

    !!! example

        ```python
        cldyn.fit(model, frames, loss=keyvision.Reconstruction(), steps=2000, key=key,
                  batching=cldyn.Windows(32, 1), loop=cldyn.HostLoop())
        ```
    """

    def run(self, params, opt_state, static, data, key, start, count, *, loss, optimizer, batching,
            length, sharding):
        """See `AbstractStepLoop`."""
        del length  # the losses of a chunk are stacked, whatever its length
        # placed as the parameters are (committed): the step's own outputs are, and a first call with
        # uncommitted ones would compile the step a second time
        leaves = jax.tree.leaves(params)
        placement = leaves[0].sharding if leaves else None
        bad = jax.device_put(jnp.array(False), placement)
        done = jax.device_put(jnp.zeros((), jnp.int32), placement)
        values = []
        for index in range(start, start + count):
            params, opt_state, value, bad, done = _host_step(
                params, opt_state, static, data, key, jnp.asarray(index), bad, done,
                loss=loss, optimizer=optimizer, batching=batching, sharding=sharding,
            )
            values.append(value)
        return params, opt_state, jnp.stack(values), done, bad
