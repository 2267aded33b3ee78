"""Small dense linear algebra for the hot path of eq. 6.

The multiplier system `DPhi M^-1 DPhi^T lambda = -b` is tiny (one row per constraint) and is solved once
per acceleration, usually under `jax.vmap`. On CPU a batched LAPACK call loops over the batch one matrix
at a time, which costs more than the rest of the dynamics together; an unrolled factorisation of a
small matrix is a handful of elementwise operations that XLA vectorises across the batch. Larger
systems go to lineax.
"""

import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Float

# Unrolling costs O(n^3) traced operations; beyond this size lineax is the better deal.
_UNROLL_MAX = 12


def psd_solve(
    matrix: Float[Array, "n n"], rhs: Float[Array, "n ..."]
) -> Float[Array, "n ..."]:
    """Solve `A z = rhs` for a symmetric positive semi-definite `A`.

    A pivot that is numerically zero (a redundant row, such as the same constraint given twice) gets
    a zero component in `z`, so a consistent singular system gets an exact solution and the
    result is always finite. This is not the minimum-norm solution; `A z` is what it guarantees.
    """
    n = matrix.shape[0]
    if n == 0:
        return rhs
    if n > _UNROLL_MAX:
        operator = lx.MatrixLinearOperator(matrix, lx.positive_semidefinite_tag)
        if rhs.ndim == 1:
            return lx.linear_solve(operator, rhs, lx.SVD()).value
        solve = lambda column: lx.linear_solve(operator, column, lx.SVD()).value
        return jnp.stack([solve(rhs[:, j]) for j in range(rhs.shape[1])], axis=1)
    tol = 100 * n * jnp.finfo(matrix.dtype).eps
    lower = [[None] * n for _ in range(n)]
    pivot_inv = [None] * n
    pivot = [None] * n
    for j in range(n):
        d = matrix[j, j] - sum(lower[j][q] ** 2 * pivot[q] for q in range(j))
        ok = d > tol * jnp.abs(matrix[j, j])
        pivot[j] = jnp.where(ok, d, 0.0)
        pivot_inv[j] = jnp.where(ok, 1.0 / jnp.where(ok, d, 1.0), 0.0)
        for i in range(j + 1, n):
            s = matrix[i, j] - sum(lower[i][q] * lower[j][q] * pivot[q] for q in range(j))
            lower[i][j] = s * pivot_inv[j]
    y = [None] * n
    for i in range(n):
        y[i] = rhs[i] - sum(lower[i][q] * y[q] for q in range(i))
    z = [y[i] * pivot_inv[i] for i in range(n)]
    out = [None] * n
    for i in reversed(range(n)):
        out[i] = z[i] - sum(lower[q][i] * out[q] for q in range(i + 1, n))
    return jnp.stack(out)
