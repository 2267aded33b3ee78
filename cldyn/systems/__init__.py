"""Analytic planar mechanisms in keypoint coordinates.

Each builder returns `(system, joints)`: a `ConstrainedLagrangian` and, where minimal coordinates exist,
the `JointMap` between joint coordinates `(q, qd)` and keypoints `(x, xd)` (`None` for closed loops).
Angles are measured counter-clockwise from hanging straight down; gravity points along `-y`.
"""

from ._builders import (
    acrobot as acrobot,
    cartpole as cartpole,
    chain as chain,
    four_bar as four_bar,
    pendulum as pendulum,
)
