"""The swept SDOF model's numerics: the prefix-scan recursion against the sequential one, the
envelope's derivatives and the variable-projection Jacobian against central differences."""

import math

import numpy as np
import pytest

from bttsim_stream.process.swept import SweptForcing, first_order

TWO_PI = 2.0 * math.pi


def _sequential(lam_h, x, y0):
    a, y, out = np.exp(lam_h), y0, np.empty(len(x), complex)
    for m, xm in enumerate(x):
        y = a * y + xm
        out[m] = y
    return out


@pytest.mark.parametrize("m", [0, 1, 2, 3, 31, 32, 33, 1000, 4097])
@pytest.mark.parametrize("decay", [0.0, 1e-4, 0.05, 2.0])
def test_scan_is_the_recursion(m, decay):
    rng = np.random.default_rng(m + int(decay * 1e4))
    lam_h = complex(-decay, rng.uniform(-3, 3))
    x = rng.normal(size=m) + 1j * rng.normal(size=m)
    y0 = complex(rng.normal(), rng.normal())
    got = first_order(lam_h, x, y0)
    assert got.shape == (m,)
    if m:
        ref = _sequential(lam_h, x, y0)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * np.abs(ref).max())


def test_scan_of_several_rows_is_each_row():
    rng = np.random.default_rng(3)
    lam_h = np.array([-0.01 + 0.5j, -0.01 - 0.5j, -1.0 + 2.0j])
    x = rng.normal(size=(3, 500)) + 1j * rng.normal(size=(3, 500))
    y0 = np.array([1.0, 2.0j, -1.0])
    got = first_order(lam_h, x, y0)
    for k in range(3):
        np.testing.assert_allclose(got[k], _sequential(lam_h[k], x[k], y0[k]), rtol=1e-12, atol=1e-12)


def _case(seed=1):
    rng = np.random.default_rng(seed)
    grid = np.linspace(0.0, 1.5, 12_001)
    phi = 8 * (2560 * TWO_PI / 60 * grid + 0.5 * 30 * TWO_PI / 60 * grid ** 2)
    forcing = SweptForcing(grid, phi)
    ts = np.sort(rng.uniform(0.1, 1.4, 150))
    z = forcing.envelope(342.5, 0.012)
    zt = np.interp(ts, grid, z.real) + 1j * np.interp(ts, grid, z.imag)
    yn = (0.7 + 0.2j) * zt / np.abs(zt).max() + 0.05 + 0.01 * (rng.normal(size=ts.size) + 1j * rng.normal(size=ts.size))
    forcing.clear()
    return forcing, ts, yn / np.abs(yn).max()


def test_envelope_derivatives_are_central_differences():
    forcing, _, _ = _case()
    fn, zeta = 342.0, 0.011
    _, d_fn, d_zeta = forcing.derivatives(fn, zeta)
    for d, (q_plus, q_minus, step) in ((d_fn, ((fn + 1e-4, zeta), (fn - 1e-4, zeta), 2e-4)),
                                       (d_zeta, ((fn, zeta + 1e-8), (fn, zeta - 1e-8), 2e-8))):
        fd = (SweptForcing(forcing.grid, forcing.phi).envelope(*q_plus)
              - SweptForcing(forcing.grid, forcing.phi).envelope(*q_minus)) / step
        assert np.abs(fd - d).max() <= 1e-5 * np.abs(d).max()


def test_projection_jacobian_is_central_differences():
    """The variable-projection Jacobian (the linear part re-solved at every trial) against
    central differences of the residuals."""
    forcing, ts, yn = _case()
    q = np.array([342.0, 0.011])
    J = forcing.jacobian(q, ts, yn)

    def resid(p):
        r = forcing.solve(p, ts, yn)[2]
        return np.concatenate([r.real, r.imag])

    for k, step in enumerate((1e-4, 1e-8)):
        e = np.zeros(2)
        e[k] = step
        fd = (resid(q + e) - resid(q - e)) / (2 * step)
        assert np.abs(fd - J[:, k]).max() <= 1e-5 * np.abs(J[:, k]).max()


def test_fit_recovers_the_model():
    forcing, ts, yn = _case()
    res = forcing.fit(ts, yn, 341.0, 0.02)
    assert res.x[0] == pytest.approx(342.5, rel=2e-4)
    assert res.x[1] == pytest.approx(0.012, rel=0.05)
