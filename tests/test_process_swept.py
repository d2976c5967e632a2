"""The swept SDOF model's numerics: the prefix-scan recursion against the sequential one, the
envelope's derivatives and the variable-projection Jacobian against central differences."""

import math

import numpy as np
import pytest

from bttsim_stream.process.swept import SweptForcing, first_order
from bttsim_stream.process.varpro import linear_part, projected_jacobian

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


def _rows(forcing, truth, seed=2):
    """Several blades' noisy samples of the model, of different lengths (packed rows)."""
    rng = np.random.default_rng(seed)
    m = [150, 90, 120]
    ts = np.full((len(truth), max(m)), forcing.grid[0])
    yn = np.zeros(ts.shape, complex)
    w = np.zeros(ts.shape, bool)
    for j, ((fn, zeta), mj) in enumerate(zip(truth, m)):
        t = np.sort(rng.uniform(0.1, 1.4, mj))
        z = forcing.envelope(fn, zeta)
        zt = np.interp(t, forcing.grid, z.real) + 1j * np.interp(t, forcing.grid, z.imag)
        y = (0.7 + 0.2j) * zt / np.abs(zt).max() + 0.05 + 0.01 * (rng.normal(size=mj) + 1j * rng.normal(size=mj))
        ts[j, :mj], yn[j, :mj], w[j, :mj] = t, y / np.abs(y).max(), True
    return ts, yn, w


TRUTH = [(342.5, 0.012), (343.4, 0.008), (341.8, 0.02)]


def test_envelope_at_samples_is_numpy_interp():
    forcing, _, _ = _case()
    ts, _, w = _rows(forcing, TRUTH)
    fn, zeta = np.array([342.0, 343.0, 341.0]), np.array([0.011, 0.009, 0.018])
    z, dz, peak, z_peak = forcing.at(fn, zeta, ts, derivatives=True)
    for j in range(3):
        zj, d_fn, d_zeta = forcing.derivatives(fn[j], zeta[j])
        for got, ref in ((z[j], zj), (dz[j, :, 0], d_fn), (dz[j, :, 1], d_zeta)):
            want = np.interp(ts[j], forcing.grid, ref.real) + 1j * np.interp(ts[j], forcing.grid, ref.imag)
            np.testing.assert_allclose(got[w[j]], want[w[j]], rtol=1e-12, atol=1e-12 * np.abs(ref).max())
        assert peak[j] == np.argmax(np.abs(zj)) and z_peak[j] == zj[peak[j]]


def test_projection_jacobian_is_central_differences():
    """The variable-projection Jacobian (the linear part re-solved at every trial) against
    central differences of the residuals, for several blades at once."""
    forcing, _, _ = _case()
    ts, yn, w = _rows(forcing, TRUTH)
    q = np.array([[342.0, 0.011], [343.0, 0.009], [341.0, 0.018]])

    def resid(p):
        z, _, _, _ = forcing.at(p[:, 0], p[:, 1], ts)
        return linear_part(z, yn, w).r

    z, dz, _, _ = forcing.at(q[:, 0], q[:, 1], ts, derivatives=True)
    cols = projected_jacobian(linear_part(z, yn, w), dz, w)
    for k, step in enumerate((1e-4, 1e-8)):
        e = np.zeros(2)
        e[k] = step
        fd = (resid(q + e) - resid(q - e)) / (2 * step)
        for j in range(3):
            assert np.abs(fd[j] - cols[j, :, k]).max() <= 1e-5 * np.abs(cols[j, :, k]).max()
        assert not np.any(cols[~w])


def test_fit_recovers_the_model_and_matches_least_squares():
    """Each blade's fit finds the model it was drawn from, and the minimum that
    ``scipy.optimize.least_squares`` finds on the same residuals."""
    from scipy.optimize import least_squares

    forcing, _, _ = _case()
    ts, yn, w = _rows(forcing, TRUTH)
    fn0 = np.array([341.0, 344.0, 342.5])
    res = forcing.fit(ts, yn, w, fn0, 0.015)
    assert res.ok.all()
    for j, (fn, zeta) in enumerate(TRUTH):
        assert res.q[j, 0] == pytest.approx(fn, rel=1e-3)
        assert res.q[j, 1] == pytest.approx(zeta, rel=0.15)

        def r(p, j=j):
            z, _, _, _ = forcing.at(np.array([p[0]]), np.array([p[1]]), ts[j:j + 1])
            rr = linear_part(z, yn[j:j + 1], w[j:j + 1]).r[0]
            return np.concatenate([rr.real, rr.imag])

        ref = least_squares(r, [fn0[j], 0.015], x_scale=[fn0[j] * 0.0015, 0.0015],
                            bounds=([0.8 * fn0[j], 1e-5], [1.2 * fn0[j], 0.3]), xtol=1e-12, ftol=1e-12)
        assert res.q[j, 0] == pytest.approx(ref.x[0], rel=1e-8)
        assert res.q[j, 1] == pytest.approx(ref.x[1], rel=1e-5)
        jtj = ref.jac.T @ ref.jac
        np.testing.assert_allclose(res.jtj[j], jtj, rtol=1e-5, atol=1e-5 * math.sqrt(jtj[0, 0] * jtj[1, 1]))


def test_a_blade_fits_alike_alone_and_with_others():
    forcing, _, _ = _case()
    ts, yn, w = _rows(forcing, TRUTH)
    fn0 = np.array([341.0, 344.0, 342.5])
    together = forcing.fit(ts, yn, w, fn0, 0.015)
    for j in range(3):
        alone = forcing.fit(ts[j:j + 1], yn[j:j + 1], w[j:j + 1], fn0[j:j + 1], 0.015)
        np.testing.assert_allclose(alone.q[0], together.q[j], rtol=1e-12)


@pytest.mark.parametrize("steps", [997, 4096])
def test_segments_join_into_one_integration(monkeypatch, steps):
    """A long crossing is integrated in time segments, each from the previous one's last
    value: the envelopes, derivatives and peaks equal one integration of the whole grid."""
    from bttsim_stream.process import swept

    forcing, ts, _ = _case()
    fn, zeta = np.array([342.5, 343.5, 344.5]), np.array([0.012, 0.004, 0.008])
    rows = np.stack([ts, ts, np.sort(ts * 0.5 + 0.3)])
    whole = forcing.at(fn, zeta, rows, derivatives=True)
    z_whole = forcing.envelope(342.5, 0.012)
    assert len(forcing._segments()) == 1
    monkeypatch.setattr(swept, "SEGMENT_STEPS", steps)
    assert len(forcing._segments()) == -(-(forcing.grid.size - 1) // steps)
    got = forcing.at(fn, zeta, rows, derivatives=True)
    for a, b in zip(got[:2], whole[:2]):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-11 * np.abs(b).max())
    np.testing.assert_array_equal(got[2], whole[2])  # the peak: inside the grid, not at a join
    assert 0 < whole[2].min() and whole[2].max() < forcing.grid.size - 1
    np.testing.assert_allclose(got[3], whole[3], rtol=1e-11)
    np.testing.assert_allclose(forcing.envelope(342.5, 0.012), z_whole, rtol=0, atol=1e-11 * np.abs(z_whole).max())


def test_blades_fitted_in_groups_fit_as_one(monkeypatch):
    """A long crossing's blades are fitted in groups (each blade's fit is its own): the same
    numbers as all at once, also where a group holds a blade that cannot start."""
    from bttsim_stream.process import swept

    forcing, _, _ = _case()
    ts, yn, w = _rows(forcing, TRUTH)
    fn0 = np.array([341.0, 344.0, 342.5])
    fn0_bad = fn0.copy()
    fn0_bad[2] = np.nan
    for start in (fn0, fn0_bad):
        together = forcing.fit(ts, yn, w, start, 0.015)
        monkeypatch.setattr(swept, "FIT_SAMPLES", ts.shape[1] * 2)
        grouped = forcing.fit(ts, yn, w, start, 0.015)
        monkeypatch.undo()
        for a, b in zip((grouped.q, grouped.jtj, grouped.ok, grouped.steps) + grouped.extra,
                        (together.q, together.jtj, together.ok, together.steps) + together.extra):
            np.testing.assert_array_equal(a, b)


def test_blocked_sdof_equals_unblocked(monkeypatch):
    """sdof_method's blocks (the blades in groups of swept.FIT_SAMPLES samples, the grid's
    terms per segment from the phase at the points asked for, the sweep rate from 5 points
    around each peak) change no number: tiny blocks equal one block, bit for bit."""
    from bttsim_stream.process import swept
    from bttsim_stream.process.displacement import rotor_phase_from_opr
    from bttsim_stream.process.methods import sdof_method

    rng = np.random.default_rng(5)
    n_rev, nb, eo = 400, 3, 8
    omega = TWO_PI * (40.0 + 0.01 * np.arange(n_rev + 1))  # a slow run-up
    opr = np.concatenate([[0.0], np.cumsum(TWO_PI / omega[:-1])])[:n_rev]
    t = opr[:, None] + (np.arange(nb) + 0.5) / nb * (TWO_PI / omega[:n_rev, None])
    fn = eo * omega[200] / TWO_PI
    x = (eo * omega[:n_rev, None] / TWO_PI - fn) / (0.02 * fn)
    phasor = 1e-4 / (1.0 + 2j * x) + 1e-7 * (rng.normal(size=(n_rev, nb)) + 1j * rng.normal(size=(n_rev, nb)))
    phasor[10, 1] = np.nan
    args = (phasor, t, opr, rotor_phase_from_opr(opr), eo, 150, 250)
    kw = dict(fn0_hz=np.full(nb, fn * 1.002), zeta0=0.01)
    whole = sdof_method(*args, **kw)
    monkeypatch.setattr(swept, "FIT_SAMPLES", 1)
    monkeypatch.setattr(swept, "SEGMENT_STEPS", 1 << 20)  # one segment
    blocked = sdof_method(*args, **kw)
    for name in whole[0].__dataclass_fields__:
        a, b = getattr(blocked[0], name), getattr(whole[0], name)
        if isinstance(a, np.ndarray):
            assert np.array_equal(a, b, equal_nan=True), name
    assert blocked[1] == whole[1]
    assert np.isfinite(whole[0].amp_pkpk_m).all()


def test_terms_per_segment_equal_the_whole_grids():
    """SweptForcing's terms of a segment, and UniformGrid's points, are the whole grid's."""
    from bttsim_stream.process.swept import UniformGrid

    forcing, _, _ = _case()
    phi = forcing._phi(0, forcing.size)
    w = np.diff(phi) / forcing.h
    whole = (np.exp(1j * phi[:-1]), np.exp(1j * w * forcing.h), 1j * w, np.exp(-1j * phi))
    for s, e in ((0, 997), (997, 5000), (5000, forcing.size - 1)):
        t = forcing._terms(s, e)
        for a, b in zip((t.e_phi, t.e_wh, t.jw), whole[:3]):
            assert np.array_equal(a, b[s:e])
        assert np.array_equal(t.e_mphi, whole[3][s:e + 1])
    g = UniformGrid(0.25, 1e-4, 12_001)
    ref = 0.25 + 1e-4 * np.arange(12_001)
    j = np.array([0, 1, 7, 12_000])
    assert np.array_equal(g[j], ref[j]) and g[-1] == ref[-1] and g[0] == ref[0] and len(g) == ref.size


def test_phase_rates_are_the_whole_grids_gradients():
    """The sweep rate's derivatives of the phase, from 5 points around each peak, equal
    np.gradient over the whole grid (also at and next to both ends)."""
    from bttsim_stream.process.methods import _phase_rates

    size, h = 40, 0.01
    phi_all = np.cumsum(np.random.default_rng(2).uniform(1.0, 2.0, size))
    w_all = np.gradient(phi_all, h)
    rate_all = np.gradient(w_all, h)
    k = np.array([0, 1, 2, 17, size - 3, size - 2, size - 1])
    w, rate = _phase_rates(lambda j: phi_all[j], k, size, h)
    assert np.array_equal(w, w_all[k]) and np.array_equal(rate, rate_all[k])
