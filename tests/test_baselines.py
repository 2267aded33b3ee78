"""The models of KeyCLD's ablation: KeyCLD, KeyCLD-NC, NODE2, and the coupled mass matrix."""

import inspect

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import cldyn

TOL = 1e-12


def test_node2_implements_the_dynamics_interface():
    model = cldyn.SecondOrderNeuralODE(4, 2, key=jax.random.key(0))
    assert isinstance(model, cldyn.AbstractDynamics)
    assert (model.size, model.num_inputs, model.num_constraints) == (4, 2, 0)
    # paper A.4: three hidden layers of 2 * 32 units on [x, xd, u]
    assert model.mlp.in_size == 10 and model.mlp.width_size == 64 and model.mlp.depth == 3
    x, xd, u = jnp.ones(4), jnp.zeros(4), jnp.array([0.5, -1.0])
    assert model.acceleration(x, xd, u).shape == (4,)
    np.testing.assert_allclose(model.acceleration(x, xd), model.acceleration(x, xd, jnp.zeros(2)))
    with pytest.raises(ValueError, match="u must have shape"):
        model.acceleration(x, xd, jnp.zeros(3))
    batched = jax.jit(jax.vmap(model.acceleration))(jnp.ones((5, 4)), jnp.zeros((5, 4)), jnp.zeros((5, 2)))
    assert batched.shape == (5, 4)


def test_node2_and_nc_simulate_with_a_feedback_control():
    key = jax.random.key(1)
    ts = jnp.linspace(0.0, 0.2, 11)
    for model in (cldyn.SecondOrderNeuralODE(2, 1, key=key), cldyn.keycld_model(2, 1, None, key=key)):
        traj = cldyn.simulate(
            model, jnp.array([0.0, -1.0]), jnp.zeros(2), ts, control=lambda t, x, xd: -xd[:1],
            solver=cldyn.RK4(), dt0=0.02,
        )
        assert traj.x.shape == (11, 2) and bool(jnp.all(jnp.isfinite(traj.x)))


def test_keycld_model_is_the_papers_model():
    key = jax.random.key(0)
    constraint = cldyn.keycld_constraint("cartpole")
    model = cldyn.keycld_model(4, 2, constraint, key=key)
    assert isinstance(model.mass, cldyn.PointMasses) and isinstance(model.potential, cldyn.MLPPotential)
    assert isinstance(model.input_matrix, cldyn.MLPInput) and model.constraint is constraint
    np.testing.assert_allclose(model.mass.masses, jnp.ones(2))
    nc = cldyn.keycld_model(4, 2, None, key=key)
    assert nc.num_constraints == 0 and nc.acceleration(jnp.ones(4), jnp.zeros(4), jnp.ones(2)).shape == (4,)
    assert cldyn.keycld_model(2, 0, cldyn.Anchor(0), key=key).input_matrix is None
    with pytest.raises(ValueError, match="multiple of dim"):
        cldyn.keycld_model(3, 1, None, key=key)
    with pytest.raises(ValueError, match="unknown KeyCLD system"):
        cldyn.keycld_constraint("double-pendulum")
    assert cldyn.keycld_constraint("pendulum").num_constraints == 1
    assert cldyn.keycld_constraint("acrobot").num_constraints == 2
    with pytest.raises(ValueError, match="one joint per control, got 2 for num_inputs=1"):
        cldyn.keycld_model(4, 1, constraint, key=key, joints=cldyn.keycld_joints("cartpole"))
    with pytest.raises(ValueError, match="does not apply to 1 keypoints"):
        cldyn.keycld_model(2, 2, cldyn.Anchor(0), key=key, joints=cldyn.keycld_joints("acrobot"))
    with pytest.raises(ValueError, match="potential must be 'mlp' or 'gravity'"):
        cldyn.keycld_model(4, 2, constraint, key=key, potential="quadratic")
    with pytest.raises(ValueError, match="unknown KeyCLD system"):
        cldyn.keycld_joints("double-pendulum")


def test_keycld_joints_do_the_virtual_work_of_the_motors():
    # closed form: a motor on a hinge does work u dq; the keypoint force g(x) u must do the same on
    # any velocity that keeps the links' lengths (the acrobot's elbow and tip at angles a, a + b)
    a, b, l1, l2 = 0.7, -1.1, 1.3, 0.6
    elbow = l1 * jnp.array([jnp.sin(a), -jnp.cos(a)])
    x = jnp.concatenate([elbow, elbow + l2 * jnp.array([jnp.sin(a + b), -jnp.cos(a + b)])])
    ad, bd = 0.4, -0.9  # joint velocities
    elbow_d = l1 * ad * jnp.array([jnp.cos(a), jnp.sin(a)])
    xd = jnp.concatenate([elbow_d, elbow_d + l2 * (ad + bd) * jnp.array([jnp.cos(a + b), jnp.sin(a + b)])])
    g = cldyn.JointInput(cldyn.keycld_joints("acrobot"))(x)
    np.testing.assert_allclose(xd @ g, [ad, bd], rtol=1e-5)
    # the cart-pole: slide s of the cart, pole at angle p from straight down
    s, p, sd, pd = 0.3, 2.0, -0.5, 1.7
    x = jnp.array([s, 0.0, s + l2 * jnp.sin(p), -l2 * jnp.cos(p)])
    xd = jnp.array([sd, 0.0, sd + l2 * pd * jnp.cos(p), l2 * pd * jnp.sin(p)])
    np.testing.assert_allclose(xd @ cldyn.JointInput(cldyn.keycld_joints("cartpole"))(x), [sd, pd], rtol=1e-5)


def test_coupled_masses_are_point_masses_when_diagonal_and_exact_for_a_rod():
    masses = jnp.array([1.5, 0.5])
    coupled, point = cldyn.CoupledMasses(masses), cldyn.PointMasses(masses)
    np.testing.assert_allclose(coupled.matrix(), point.matrix(), atol=TOL)
    # a uniform rod between two keypoints: T = 1/2 m |v_c|^2 + 1/2 (m L^2 / 12) omega^2
    m = 1.2
    block = cldyn.rigid_body_mass(m, m / 12, com=[0.5, 0.0], points=[[0.0, 0.0], [1.0, 0.0]])
    a = np.asarray(block)[::2, ::2]
    rod = eqx.tree_at(
        lambda c: (c.log_diagonal, c.lower),
        coupled,
        (jnp.log(jnp.diag(jnp.linalg.cholesky(a))), jnp.linalg.cholesky(a)),
    )
    np.testing.assert_allclose(rod.matrix(), block, atol=TOL)
    v = jnp.array([0.3, -1.0, 2.0, 0.5])
    b = jnp.stack([v, 2 * v], axis=1)
    np.testing.assert_allclose(rod.matvec(v), block @ v, atol=TOL)
    np.testing.assert_allclose(rod.solve(b), np.linalg.solve(block, b), atol=1e-10)
    np.testing.assert_allclose(rod.inverse() @ block, np.eye(4), atol=1e-10)
    model = cldyn.keycld_model(4, 1, cldyn.Distance(0, 1), key=jax.random.key(0), mass="coupled")
    assert isinstance(model.mass, cldyn.CoupledMasses)


def test_modules_are_abstract_or_final():
    # STYLE 4: a subclassed module is abstract; every concrete one is final
    modules = [
        obj for module in (cldyn._loss, cldyn._batching, cldyn._progress, cldyn._baselines, cldyn._evaluate)
        for _, obj in inspect.getmembers(module, inspect.isclass)
        if issubclass(obj, eqx.Module) and obj.__module__ == module.__name__
    ]
    for cls in modules:
        children = [c for c in modules if c is not cls and issubclass(c, cls)]
        if children:
            assert inspect.isabstract(cls), f"{cls.__name__} is subclassed but not abstract"
