"""Small dense linear algebra for the inner loops of eq. 6 and of the projections.

The multiplier system `DPhi M^-1 DPhi^T lambda = -b` is tiny (one row per constraint) and is solved
once per acceleration, usually under `jax.vmap`. On CPU a batched LAPACK call loops over the batch
one matrix at a time, which costs more than the rest of the dynamics together; an unrolled
factorisation of a small matrix is a handful of elementwise operations that XLA vectorises across
the batch. Larger systems go to lineax.
"""

from typing import Any

import equinox as eqx
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Float

# Unrolling costs O(n^3) traced operations (O(n) for a product); beyond this size lineax (a dot) is the
# better deal.
UNROLL_MAX = 12


def small_matmul(a: Float[Array, "n k"] | Float[Array, " k"], b: Float[Array, "k ..."]) -> Array:
    """`a @ b` for a small contracted dimension `k`, written out as `k` multiply-adds.

    In the integrator's inner loop every `dot` is a kernel (a library call) of its own, while
    multiply-adds fuse with the elementwise work around them; on CPU this makes a projected RK4
    step of the acrobot about twice as fast for one trajectory and no slower under `jax.vmap`.
    Beyond `UNROLL_MAX` the product is an ordinary `dot`.
    """
    k = a.shape[-1]
    if k > UNROLL_MAX or b.shape[0] != k:
        return a @ b
    if a.ndim == 1:
        column = lambda j: a[j]
        expand = lambda v: v
    else:
        column = lambda j: a[:, j].reshape((a.shape[0],) + (1,) * (b.ndim - 1))
        expand = lambda v: v[None]
    out = column(0) * expand(b[0])
    for j in range(1, k):
        out = out + column(j) * expand(b[j])
    return out


def small_solve(matrix: Float[Array, "n n"], rhs: Float[Array, "n ..."]) -> Float[Array, "n ..."]:
    """Solve `A z = rhs` for a small square `A` by an unrolled LU factorisation without pivoting.

    Meant for matrices that are (close to) symmetric positive semi-definite, such as
    `DPhi M^-1 DPhi^T`, where pivoting is unnecessary. A pivot that is numerically zero (a redundant
    row, such as the same constraint given twice) gets a zero component in `z`, so a consistent
    singular system gets an exact solution and the result is always finite. This is not the
    minimum-norm solution; `A z = rhs` is what it guarantees. Above `UNROLL_MAX` rows, lineax's SVD
    solve (least squares, minimum norm) is used instead.
    """
    n = matrix.shape[0]
    if n == 0:
        return rhs
    if n > UNROLL_MAX:
        operator = lx.MatrixLinearOperator(matrix)
        if rhs.ndim == 1:
            return lx.linear_solve(operator, rhs, lx.SVD()).value
        columns = [lx.linear_solve(operator, rhs[:, j], lx.SVD()).value for j in range(rhs.shape[1])]
        return jnp.stack(columns, axis=1)
    tol = 100 * n * jnp.finfo(matrix.dtype).eps
    a = [[matrix[i, j] for j in range(n)] for i in range(n)]
    lower = [[None] * n for _ in range(n)]
    upper = [[None] * n for _ in range(n)]
    pivot_inv = [None] * n
    for j in range(n):
        for q in range(j, n):  # row j of U
            upper[j][q] = a[j][q] - sum(lower[j][p] * upper[p][q] for p in range(j))
        pivot = upper[j][j]
        ok = jnp.abs(pivot) > tol * jnp.abs(a[j][j])
        pivot_inv[j] = jnp.where(ok, 1.0 / jnp.where(ok, pivot, 1.0), 0.0)
        for i in range(j + 1, n):  # column j of L
            lower[i][j] = (a[i][j] - sum(lower[i][p] * upper[p][j] for p in range(j))) * pivot_inv[j]
    y = [None] * n
    for i in range(n):
        y[i] = rhs[i] - sum(lower[i][p] * y[p] for p in range(i))
    out = [None] * n
    for i in reversed(range(n)):
        out[i] = (y[i] - sum(upper[i][p] * out[p] for p in range(i + 1, n))) * pivot_inv[i]
    return jnp.stack(out)


class SmallDense(lx.AbstractLinearSolver):
    """A lineax solver for small dense systems, vectorised under `jax.vmap` (see `small_solve`).

    Used as the linear solver of optimistix's Newton iterations in the projections.
    """

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]):
        del options
        if operator.in_size() != operator.out_size():
            raise ValueError("SmallDense needs a square operator")
        return operator.as_matrix(), eqx.internal.Static(False)

    def compute(self, state, vector, options: dict[str, Any]):
        del options
        matrix, transposed = state
        if transposed.value:
            matrix = matrix.T
        return small_solve(matrix, vector), lx.RESULTS.successful, {}

    def transpose(self, state, options: dict[str, Any]):
        matrix, transposed = state
        return (matrix, eqx.internal.Static(not transposed.value)), options

    def conj(self, state, options: dict[str, Any]):
        matrix, transposed = state
        return (matrix.conj(), transposed), options

    def assume_full_rank(self) -> bool:
        return True
