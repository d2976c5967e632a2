"""The batched variable-projection fit (:mod:`bttsim_stream.process.varpro`): the linear part
against ``numpy.linalg.lstsq``, the minimum against ``scipy.optimize.least_squares`` on a
model with an analytic answer, and the rows that cannot start."""

import numpy as np
import pytest

from bttsim_stream.process.varpro import fit_blades, inverse2, linear_part, projected_jacobian


def test_linear_part_is_lstsq_per_row():
    rng = np.random.default_rng(0)
    z = rng.normal(size=(4, 30)) + 1j * rng.normal(size=(4, 30))
    y = rng.normal(size=(4, 30)) + 1j * rng.normal(size=(4, 30))
    w = np.ones((4, 30), bool)
    w[1, 20:] = w[3, 9:] = False
    lp = linear_part(z, y, w)
    for j in range(4):
        A = np.stack([z[j, w[j]], np.ones(w[j].sum())], axis=1)
        (C, c), *_ = np.linalg.lstsq(A, y[j, w[j]], rcond=None)
        assert lp.C[j] == pytest.approx(C, rel=1e-12) and lp.c[j] == pytest.approx(c, rel=1e-12)
        np.testing.assert_allclose(lp.r[j, w[j]], A @ [C, c] - y[j, w[j]], atol=1e-12)
        assert 1.0 / lp.nz2[j] == pytest.approx(np.linalg.inv(A.conj().T @ A)[0, 0].real, rel=1e-12)
    assert not np.any(lp.r[~w])


def _decay(t, w):
    """``y = C exp(-a t) + c`` with ``q = (a, b)``, ``z = exp(-(a + i b) t)``: a model with
    derivatives in closed form."""

    def model(q, rows):
        tt = t[rows]
        z = np.exp(-(q[:, :1] + 1j * q[:, 1:]) * tt)
        dz = np.stack([-tt * z, -1j * tt * z], axis=-1)
        lp = linear_part(z, y[rows], w[rows])
        return lp, projected_jacobian(lp, dz, w[rows]), (z,)

    rng = np.random.default_rng(4)
    truth = np.array([[2.0, 5.0], [0.5, 9.0], [1.2, 3.0]])
    y = (1.5 - 0.5j) * np.exp(-(truth[:, :1] + 1j * truth[:, 1:]) * t) + 0.2 + 0.01 * rng.normal(size=t.shape)
    return model, y, truth


def test_the_minimum_is_least_squares_and_the_bounds_hold():
    from scipy.optimize import least_squares

    t = np.tile(np.linspace(0.0, 2.0, 60), (3, 1))
    w = np.ones(t.shape, bool)
    model, y, truth = _decay(t, w)
    q0 = np.array([[1.5, 4.5], [0.7, 8.5], [1.0, 3.5]])
    lower, upper = q0 * 0.5, q0 * 1.5
    res = fit_blades(model, q0, lower, upper, np.full((3, 2), 0.1))
    assert res.ok.all()
    np.testing.assert_array_equal(res.extra[0], model(res.q, np.arange(3))[2][0])  # kept for the final point
    for j in range(3):
        def r(p, j=j):
            rr = model(np.array([p]), np.array([j]))[0].r[0]
            return np.concatenate([rr.real, rr.imag])

        ref = least_squares(r, q0[j], bounds=(lower[j], upper[j]), x_scale=[0.1, 0.1], xtol=1e-14, ftol=1e-14)
        np.testing.assert_allclose(res.q[j], ref.x, rtol=1e-7)
        np.testing.assert_allclose(res.q[j], truth[j], rtol=0.02)
    upper[0, 0] = 1.8  # the minimum (a = 2) is beyond: the fit ends on the bound
    res = fit_blades(model, q0, lower, upper, np.full((3, 2), 0.1))
    assert res.q[0, 0] == 1.8 and np.all(res.q <= upper) and np.all(res.q >= lower)


def test_rows_that_cannot_start_are_not_fitted():
    t = np.tile(np.linspace(0.0, 2.0, 60), (3, 1))
    w = np.ones(t.shape, bool)
    model, _, _ = _decay(t, w)
    q0 = np.array([[1.5, 4.5], [0.7, 8.5], [np.nan, 3.5]])
    lower, upper = q0 * 0.5, q0 * 1.5
    lower[1, 0] = 0.8  # the start outside the bounds
    res = fit_blades(model, q0, lower, upper, np.full((3, 2), 0.1))
    assert res.ok.tolist() == [True, False, False]
    assert np.isnan(res.q[1:]).all() and np.isfinite(res.q[0]).all()


def test_inverse2():
    a = np.array([[[4.0, 1.0], [1.0, 3.0]], [[1.0, 2.0], [2.0, 4.0]]])
    inv = inverse2(a)
    np.testing.assert_allclose(inv[0], np.linalg.inv(a[0]), rtol=1e-15)
    assert np.isnan(inv[1]).all()  # singular
