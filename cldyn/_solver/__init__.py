"""Solvers for `simulate` and `diffrax.diffeqsolve`: the term of eq. 6, RK4, RATTLE, projected steps."""

from .projected import ProjectedSolver as ProjectedSolver
from .rattle import RATTLE as RATTLE, RATTLE4 as RATTLE4
from .rk4 import RK4 as RK4
from .term import DynamicsTerm as DynamicsTerm
