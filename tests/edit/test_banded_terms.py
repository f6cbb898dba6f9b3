"""The banded solve's residual terms (design §6.5, §12.2): one contract over every member.

For every :class:`~mtex_jax.edit.ResidualTerm` member, the Gauss–Newton model its rows build
has the gradient of the term's own cost: ``Σ Jᵀ w r = ∇_y cost`` (for a robust term, the
iteratively reweighted weights ``w = ρ'/r`` give exactly that). The reference is reverse-mode
autodiff of the cost through the positions, independent of the rows' forward products,
gathers and scatters. A member left out of the registry below fails the registry test.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mtex_jax import edit as E
from mtex_jax.edit._jacobians import frame_columns
from mtex_jax.tracking import Camera, FloorContact, Reprojection

T, D, K = 7, 5, 4


def _kinematics(rng):
    W = jnp.asarray(rng.standard_normal((K, 3, D)) / np.sqrt(D))
    return lambda Y: jnp.tanh(jnp.einsum("kcd,td->tkc", W, Y)) + jnp.asarray([0.0, 0.0, 0.5])


def _camera():
    R = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # looks along +y, z up
    return Camera(
        rotation=jnp.asarray(R),
        translation=jnp.asarray([0.0, 0.3, 4.0]),
        focal=jnp.asarray(1000.0),
        center=jnp.asarray([320.0, 240.0]),
    )


def _members(rng, P):
    """One instance of every member, with parameters that make its rows non-trivial."""
    F = 2
    fm_slots = rng.integers(0, K, F)
    n_sp = 3
    points = E.PointTargets(
        slot=jnp.asarray(
            np.concatenate([rng.integers(0, K, n_sp), np.tile(fm_slots, T)]), jnp.int32
        ),
        frame=jnp.asarray(
            np.concatenate([rng.integers(0, T, n_sp), np.repeat(np.arange(T), F)]), jnp.int32
        ),
        target=jnp.asarray(0.3 * rng.standard_normal((n_sp + T * F, 3))),
        weight=jnp.asarray(rng.uniform(0.5, 3.0, (n_sp + T * F, 3))),
        exact=jnp.asarray(rng.uniform(size=n_sp + T * F) < 0.5),
        n_sparse=n_sp,
        per_frame=F,
    )
    h = np.asarray(P[..., 2])
    bounds = E.HeightBounds(
        lower=jnp.asarray(np.where(h < np.median(h), np.median(h), -np.inf)),
        weight=jnp.asarray(7.0),
        up=2,
        exact=jnp.asarray(h < np.median(h)),
    )
    cam = _camera()
    pix = jax.vmap(cam.project)(P[:, :3]) + jnp.asarray(5.0 * rng.standard_normal((T, 3, 2)))
    reproj = Reprojection(
        camera=cam,
        slots=(0, 1, 2),
        observations=pix,
        confidence=jnp.asarray(rng.uniform(0.2, 1.0, (T, 3))),
        sigma=jnp.asarray(2.0),
    )
    floor = FloorContact(slots=(2, 3), up=2, height=jnp.asarray(0.4), valid=jnp.ones(T))
    return {
        "PointTargets": points,
        "HeightBounds": bounds,
        "Reprojection": reproj,
        "FloorContact": floor,
    }


def _all_members() -> set[str]:
    """Every concrete ResidualTerm member the package exports."""
    import mtex_jax.edit as edit_pkg
    import mtex_jax.tracking as track_pkg

    out = set()
    for pkg in (edit_pkg, track_pkg):
        for name in pkg.__all__:
            obj = getattr(pkg, name)
            if (
                isinstance(obj, type)
                and issubclass(obj, E.ResidualTerm)
                and not getattr(obj, "__abstractmethods__", None)
            ):
                out.add(name)
    return out


def test_the_contract_runs_over_every_member():
    rng = np.random.default_rng(0)
    fn = _kinematics(rng)
    members = _members(rng, fn(jnp.zeros((T, D))))
    assert set(members) == _all_members()


@pytest.mark.parametrize("name", ["PointTargets", "HeightBounds", "Reprojection", "FloorContact"])
def test_rows_have_the_gradient_of_the_cost(name):
    rng = np.random.default_rng(1)
    fn = _kinematics(rng)
    Y = jnp.asarray(0.5 * rng.standard_normal((T, D)))
    term = _members(np.random.default_rng(2), fn(Y))[name]
    shift = jax.tree.map(lambda a: 0.01 * jnp.ones_like(a), term.start())
    free = jnp.ones(D)
    fc = frame_columns(fn, Y, free)
    cols = E.Columns(P=fc.P, fc=fc)
    rows = term.rows(fc.P, cols, shift)
    assert rows, "a member with no rows"
    g = jnp.zeros((T, D))
    for r in rows:
        if r.frame is None:
            g = g + jnp.einsum("trd,tr->td", r.J, r.r)
        else:
            g = g.at[r.frame].add(jnp.einsum("prd,pr->pd", r.J, r.w * r.r))
    ref = jax.grad(lambda Y: term.cost(fn(Y), shift))(Y)
    assert float(jnp.max(jnp.abs(ref))) > 1e-3  # the term is active here
    np.testing.assert_allclose(np.asarray(g), np.asarray(ref), rtol=1e-9, atol=1e-9)
    # the model's Hessian is symmetric positive semi-definite per frame
    A = sum(jnp.einsum("trd,tre->tde", r.J, r.J) for r in rows if r.frame is None)
    if not isinstance(A, int):
        assert float(jnp.min(jnp.linalg.eigvalsh(A))) > -1e-9


def test_next_round_moves_the_shift_by_the_remaining_error():
    """Point targets marked exact are shifted by their error, the rest not; bounds by their
    violation (never below 0), with no round needed once none is violated beyond ``tol``."""
    rng = np.random.default_rng(3)
    fn = _kinematics(rng)
    P = fn(jnp.asarray(0.5 * rng.standard_normal((T, D))))
    m = _members(np.random.default_rng(4), P)
    pts, bounds = m["PointTargets"], m["HeightBounds"]
    s, need = pts.next_round(P, pts.start())
    err = np.asarray(P[pts.frame, pts.slot] - pts.target)
    ex = np.asarray(pts.exact)
    np.testing.assert_allclose(np.asarray(s)[ex], -err[ex])
    assert np.all(np.asarray(s)[~ex] == 0) and bool(need)
    s, need = bounds.next_round(P, bounds.start())
    gap = np.asarray(bounds.lower - P[..., 2])
    np.testing.assert_allclose(np.asarray(s), np.maximum(gap, 0.0))
    assert bool(need)
    raised = P.at[..., 2].add(10.0)
    assert not bool(bounds.next_round(raised, bounds.start())[1])
    assert not bool(m["Reprojection"].next_round(P, ())[1])
