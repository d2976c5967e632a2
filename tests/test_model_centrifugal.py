"""Centrifugal effects (stress stiffening, spin softening) against independent truth.

* the elements: Euler buckling of a cantilever (geometric stiffness), the translational
  consistent mass (spin-softening matrix with P = I);
* a uniform rotating cantilever through the production code path (:func:`centrifugal_sector`)
  against the published flapwise frequencies (Wright, Smith, Thompson & Worley 1982; Hodges &
  Rutkowski 1981) and against an independent shooting solution of the rotating-beam ODE,
  flapwise and chordwise (chordwise = flapwise minus the in-plane softening, exactly);
* the bladed disk: the cyclic modes at speed against a direct full-wheel solve; the stored
  speed-dependent model (rows, order, alignment, smoothness).
"""

import math
from dataclasses import replace

import numpy as np
import pytest
import scipy.linalg as sla
from scipy.integrate import solve_ivp
from scipy.interpolate import CubicSpline
from scipy.optimize import brentq

from bttsim_stream import scenario as S
from bttsim_stream.errors import ScenarioError
from bttsim_stream.model import build_model
from bttsim_stream.model.beam import (BeamSection, beam_geometric_stiffness, beam_matrices, beam_spin_mass)
from bttsim_stream.model.bladed_disk import (BeamElement, BladedDiskDesign, SectorModel, assemble_full_wheel,
                                             assemble_sector, expand_cyclic, solve_cyclic)
from bttsim_stream.model.centrifugal import (assemble_full_wheel_speed, axial_force_profile, blade_alone_at_speed,
                                             centrifugal_sector, solve_cyclic_speeds, speed_grid)

SEC = BeamSection(E=200e9, G=78e9, rho=7800.0, A=1e-4, I_y=1e-9, I_z=4e-9, J=1.5e-9, I_p=5e-9)

#: Flapwise natural frequencies of a uniform rotating cantilever without hub (delta = 0),
#: lambda = omega sqrt(m L^4 / EI) at nu = Omega sqrt(m L^4 / EI): Wright et al. 1982
#: (J. Sound Vib. 82(4), Table 1), also Hodges & Rutkowski 1981 (AIAA J. 19(11)).
PUBLISHED_FLAP = {
    0.0: (3.5160, 22.0345, 61.6972),
    1.0: (3.6816, 22.1810, 61.8418),
    2.0: (4.1373, 22.6149, 62.2732),
    5.0: (6.4495, 25.4461, 65.2050),
    10.0: (11.2023, 33.6404, 74.6493),
}


def _ode_flap(nu: float, delta: float, bracket: tuple[float, float]) -> float:
    """Independent solve of w'''' - nu^2 (t w')' = lambda^2 w, t = delta (1 - x) + (1 - x^2) / 2,
    clamped at x = 0, free at x = 1: shooting on the two clamped-end unknowns (DOP853)."""
    def det(lam):
        def rhs(x, y):
            t, tp = delta * (1 - x) + 0.5 * (1 - x * x), -delta - x
            return [y[1], y[2], y[3], lam**2 * y[0] + nu**2 * (tp * y[1] + t * y[2])]
        ends = [solve_ivp(rhs, (0, 1), y0, method="DOP853", rtol=1e-12, atol=1e-14).y[2:, -1]
                for y0 in ([0, 0, 1, 0], [0, 0, 0, 1])]
        return ends[0][0] * ends[1][1] - ends[0][1] * ends[1][0]
    return brentq(det, *bracket, xtol=1e-12)


def _rotating_cantilever(hub_m: float, L: float = 0.5, n: int = 40):
    """A uniform cantilever along +X from the hub radius, clamped there, as a one-sector model
    (no ring couplings), flap = bending along Z (out of the plane of rotation), chord along Y."""
    xs = hub_m + np.linspace(0.0, L, n + 1)
    m = 6 * n
    K, M = np.zeros((m, m)), np.zeros((m, m))
    elements = []
    for e in range(n):
        p1, p2, yh = np.array([xs[e], 0, 0]), np.array([xs[e + 1], 0, 0]), np.array([0.0, 1.0, 0.0])
        idx = np.concatenate([np.arange(6) + 6 * (e - 1) if e else -np.ones(6, int), np.arange(6) + 6 * e])
        k, mm = beam_matrices(p1, p2, yh, SEC)
        keep = idx >= 0
        K[np.ix_(idx[keep], idx[keep])] += k[np.ix_(keep, keep)]
        M[np.ix_(idx[keep], idx[keep])] += mm[np.ix_(keep, keep)]
        elements.append(BeamElement(p1, p2, yh, SEC, idx))
    sec = SectorModel(K=K, M=M, ring_dofs=np.zeros((0, 6), int), ring_K=np.zeros((0, 12, 12)),
                      ring_M=np.zeros((0, 12, 12)), tip_map=np.zeros((1, 3, m)), tip_ref=np.zeros((1, 3)),
                      force_map=np.zeros((1, 3, m)), force_ref=np.zeros((1, 3)), blade_dofs=np.arange(m),
                      elements=tuple(elements), node_xyz=np.array([[x, 0.0, 0.0] for x in xs[1:]]))
    return sec, L


def _lambdas(sec, L, nu, direction: int, n_modes: int = 3):
    """Nondimensional frequencies of the modes moving mostly along ``direction`` (1 = Y, 2 = Z)."""
    cent = centrifugal_sector(sec, 1)
    scale = math.sqrt(SEC.rho * SEC.A * L**4 / (SEC.E * (SEC.I_y if direction == 2 else SEC.I_z)))
    Omega = nu / scale
    w2, V = sla.eigh(sec.K + Omega**2 * (cent.K_g - cent.K_s), sec.M)
    tr = V.reshape(-1, 6, V.shape[1])[:, :3]
    share = np.sum(tr[:, direction] ** 2, axis=0) / np.sum(tr ** 2, axis=(0, 1))
    sel = np.flatnonzero(share > 0.5)[:n_modes]
    return np.sqrt(w2[sel]) * scale


def test_geometric_stiffness_gives_euler_buckling_load():
    L, n = 0.6, 30
    m = 6 * n
    K, G = np.zeros((m, m)), np.zeros((m, m))
    for e in range(n):
        p1, p2 = np.array([e * L / n, 0, 0]), np.array([(e + 1) * L / n, 0, 0])
        k, _ = beam_matrices(p1, p2, np.array([0, 1.0, 0]), SEC)
        g = beam_geometric_stiffness(p1, p2, np.array([0, 1.0, 0]), SEC, -1.0)  # unit compression
        lo = 6 * e - 6
        for A, B in ((K, k), (G, g)):
            if e == 0:
                A[:6, :6] += B[6:, 6:]
            else:
                A[lo:lo + 12, lo:lo + 12] += B
    # K v = P (-G) v: the smallest P is the cantilever's Euler load pi^2 EI / (4 L^2)
    P = sla.eigh(K, -G, eigvals_only=True, subset_by_index=[0, 0])[0]
    expected = math.pi**2 * SEC.E * SEC.I_y / (4 * L**2)
    assert abs(P - expected) / expected < 1e-6


def test_spin_mass_with_identity_projector_is_the_translational_mass():
    p1, p2, yh = np.array([0.1, -0.02, 0.03]), np.array([0.14, 0.05, -0.01]), np.array([0.3, 1.0, 0.2])
    _, m = beam_matrices(p1, p2, yh, SEC)
    ms = beam_spin_mass(p1, p2, yh, SEC, np.eye(3))
    no_twist = replace(SEC, I_p=0.0)
    _, m0 = beam_matrices(p1, p2, yh, no_twist)
    np.testing.assert_allclose(ms, m0, rtol=0, atol=1e-12 * np.abs(m).max())
    # the in-plane projector removes exactly the Z part: P + (I - P) = I
    mz = beam_spin_mass(p1, p2, yh, SEC, np.diag([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(beam_spin_mass(p1, p2, yh, SEC) + mz, m0, rtol=0, atol=1e-12 * np.abs(m).max())


@pytest.mark.parametrize("nu", sorted(PUBLISHED_FLAP), ids=lambda v: f"nu{v:g}")
def test_rotating_cantilever_flapwise_matches_published(nu):
    sec, L = _rotating_cantilever(0.0)
    lam = _lambdas(sec, L, nu, direction=2)
    np.testing.assert_allclose(lam, PUBLISHED_FLAP[nu], rtol=1.2e-4)  # the table's 5 digits


@pytest.mark.parametrize("nu", [2.0, 6.0, 12.0], ids=lambda v: f"nu{v:g}")
def test_rotating_cantilever_with_hub_matches_ode_flap_and_chord(nu):
    delta = 1.0  # hub radius = blade length (the built-in blade: 1.53)
    sec, L = _rotating_cantilever(delta * 0.5)
    exact = _ode_flap(nu, delta, (3.0, 3.0 + 2.0 * nu))
    flap = _lambdas(sec, L, nu, direction=2)[0]
    assert abs(flap - exact) / exact < 2e-6
    # in the plane of rotation the same beam is softened by exactly Omega^2 (lambda^2 - nu^2)
    chord = _lambdas(sec, L, nu, direction=1)[0]
    assert abs(chord - math.sqrt(exact**2 - nu**2)) / exact < 2e-6


def test_static_prestress_is_the_centrifugal_load():
    hub = 0.3
    sec, L = _rotating_cantilever(hub)
    cent = centrifugal_sector(sec, 1)
    root = axial_force_profile(sec.elements[0], cent.axial_force_n[0])
    tip = axial_force_profile(sec.elements[-1], cent.axial_force_n[-1])
    # at 1 rad/s: the root carries blade mass x centroid radius, the free tip nothing;
    # in between T(x) = rho A (R (L - x) + (L^2 - x^2) / 2) exactly (quadratic per element)
    expected = SEC.rho * SEC.A * L * (hub + L / 2)
    assert abs(root[0] - expected) / expected < 1e-12
    assert abs(np.sum(tip)) < 1e-12 * expected
    x = 0.5 * L * (1 + 1 / len(sec.elements))  # a mid-element point
    e = len(sec.elements) // 2
    c = axial_force_profile(sec.elements[e], cent.axial_force_n[e])
    xi = 0.5
    exact = SEC.rho * SEC.A * (hub * (L - x) + 0.5 * (L**2 - x**2))
    assert abs(c[0] + c[1] * xi + c[2] * xi**2 - exact) < 1e-12 * expected


@pytest.fixture(scope="module")
def disk():
    d = BladedDiskDesign()
    sec = assemble_sector(d)
    return d, sec, centrifugal_sector(sec, d.n_blades), solve_cyclic(d, sec)


def test_bladed_disk_prestress(disk):
    d, sec, cent, _ = disk
    blade = cent.axial_force_n[d.n_disk_elements:]
    # the blade root carries the whole blade's centrifugal force, the tip element almost none
    assert blade[0] > 10 * blade[-1] > 0
    assert np.all(np.diff(blade) < 0)
    assert np.all(cent.hoop_force_n > 0)  # every ring in hoop tension


def test_cyclic_at_speed_equals_direct_full_wheel_solve(disk):
    import scipy.sparse.linalg as spla
    d, sec, cent, zero = disk
    Omega = 2.0 * np.pi * 6000.0 / 60.0
    track = solve_cyclic_speeds(d, sec, cent, np.array([0.0, Omega]), zero)
    cyc = np.sort(expand_cyclic(d, track.solutions[1], fix_phase=False).freq_hz)[:2 * d.n_blades]
    K, M, _ = assemble_full_wheel(d)
    G = assemble_full_wheel_speed(d, sec, cent)
    w2 = spla.eigsh(K + Omega**2 * G, k=2 * d.n_blades, M=M, sigma=-1.0, which="LM", tol=1e-13,
                    v0=np.ones(K.shape[0]), return_eigenvectors=False)
    direct = np.sort(np.sqrt(w2) / (2 * np.pi))
    np.testing.assert_allclose(cyc, direct, rtol=1e-7)  # as the zero-speed check (Lanczos on pairs)
    # the blade-dominated end of family 1 stiffens like the blade alone (Southwell coefficient
    # K = (w^2 - w0^2) / Omega^2 within 1 %; the blade alone is checked against the ODE below)
    blade = blade_alone_at_speed(sec, cent, [0.0, Omega], 1)[:, 0]
    k_blade = (blade[1] ** 2 - blade[0] ** 2) / (Omega / (2 * np.pi)) ** 2
    f = np.array([zero.freq_hz[-1, 0], track.solutions[1].freq_hz[-1, 0]])
    k_nd14 = (f[1] ** 2 - f[0] ** 2) / (Omega / (2 * np.pi)) ** 2
    assert abs(k_nd14 / k_blade - 1) < 0.01
    assert 2.5 < k_nd14 < 4.0  # the uniform beam with this hub ratio: 1.19 + 1.56 * 1.53 - softening


def _tapered_blade_ode(d: BladedDiskDesign, Omega: float, lo_hz: float, hi_hz: float) -> float:
    """First flap frequency (Hz) of the untwisted tapered blade by shooting on
    (EI w'')'' - (T w')' - m Omega^2 sin^2(eta) w = m omega^2 w (the flap direction's in-plane
    share softens), clamped at the rim, free at the tip; EI, m, T exact polynomials."""
    from numpy.polynomial import Polynomial as Poly
    R, L, eta = d.rim_radius_m, d.span_m, d.stagger_rad
    xi = Poly([0.0, 1.0 / L])
    c = d.root_chord_m + (d.tip_chord_m - d.root_chord_m) * xi
    t = d.root_thickness_m * (1 + (d.thickness_taper - 1) * xi)
    EI, m = d.blade_E_pa * d.flap_factor * c * t**3, d.blade_rho * d.area_factor * c * t
    F = (m * Poly([R, 1.0])).integ()
    s2 = math.sin(eta) ** 2

    def det(om):
        def rhs(x, y):
            w, w1, mom, v = y
            return [w1, mom / EI(x), v + Omega**2 * (F(L) - F(x)) * w1, m(x) * (om**2 + Omega**2 * s2) * w]
        ends = [solve_ivp(rhs, (0, L), y0, method="DOP853", rtol=1e-12, atol=1e-20).y[2:, -1]
                for y0 in ([0, 0, 1, 0], [0, 0, 0, 1])]
        return ends[0][0] * ends[1][1] - ends[0][1] * ends[1][0]
    return brentq(det, 2 * np.pi * lo_hz, 2 * np.pi * hi_hz, xtol=1e-10) / (2 * np.pi)


def test_blade_southwell_coefficient_matches_tapered_beam_ode():
    """The built-in blade without pretwist (tapered, stagger 41.5 deg) against the ODE: the
    frequencies of a fine mesh to 1e-4, the Southwell coefficient of the production 12-element
    mesh to 0.3 %."""
    Omega = 2.0 * np.pi * 6000.0 / 60.0
    exact = np.array([_tapered_blade_ode(replace(BladedDiskDesign(), pretwist_rad=0.0), w, lo, hi)
                      for w, lo, hi in ((0.0, 300, 400), (Omega, 350, 450))])
    k_exact = (exact[1] ** 2 - exact[0] ** 2) / (Omega / (2 * np.pi)) ** 2
    for n_el, tol_f, tol_k in ((96, 1e-4, 3e-4), (12, 3e-3, 3e-3)):
        d = replace(BladedDiskDesign(), pretwist_rad=0.0, n_blade_elements=n_el)
        sec = assemble_sector(d)
        f = blade_alone_at_speed(sec, centrifugal_sector(sec, d.n_blades), [0.0, Omega], 1)[:, 0]
        np.testing.assert_allclose(f, exact, rtol=tol_f)
        k = (f[1] ** 2 - f[0] ** 2) / (Omega / (2 * np.pi)) ** 2
        assert abs(k / k_exact - 1) < tol_k, (n_el, k, k_exact)


def test_expanded_modes_at_speed_are_exact_full_wheel_modes(disk):
    d, sec, cent, zero = disk
    Omega = 2.0 * np.pi * 5000.0 / 60.0
    track = solve_cyclic_speeds(d, sec, cent, speed_grid(Omega, 5), zero)
    modes = expand_cyclic(d, track.solutions[-1], fix_phase=False)
    K, M, _ = assemble_full_wheel(d)
    Kw = K + Omega**2 * assemble_full_wheel_speed(d, sec, cent)
    Phi = modes.shapes.reshape(len(modes.freq_hz), -1).T
    np.testing.assert_allclose(Phi.T @ (M @ Phi), np.eye(Phi.shape[1]), atol=1e-12)
    w2 = (2 * np.pi * modes.freq_hz) ** 2
    resid = np.linalg.norm(Kw @ Phi - (M @ Phi) * w2, axis=0) / np.linalg.norm(Kw @ Phi, axis=0)
    assert resid.max() < 2e-7  # the zero-speed modes: 7e-8 (the dense solver on stiff axial DOF)
    assert track.min_mac > 0.999


@pytest.fixture(scope="module")
def speed_model():
    return build_model(S.Scenario(model=S.Model(centrifugal=True, centrifugal_speeds=9)))


def test_speed_model_rows_and_order(speed_model):
    m = speed_model
    zero = build_model()
    e = m.extra
    sp = e["speed_rad_s"]
    np.testing.assert_allclose(sp[-1] * 30 / np.pi, 4800.0)  # 1.2 x 4000 rpm
    assert sp.shape == (9,) and sp[0] == 0.0
    for key in ("freq_hz", "tip_shapes", "force_shapes", "campbell_freq_hz"):
        zero_arr = getattr(zero, key)
        assert np.array_equal(getattr(m, key), zero_arr)
        assert np.array_equal(e[key + "_at_speed"][0], zero_arr)
    # every mode stiffens; family 1 labels unchanged; the Campbell table is the tracked frequencies
    f = e["freq_hz_at_speed"]
    assert np.all(np.diff(f[:, m.family == 0], axis=0) > 0)
    for s in range(sp.size):
        for nd in range(15):
            sel = (m.family == 0) & (m.nodal_diameter == nd)
            np.testing.assert_allclose(f[s, sel], e["campbell_freq_hz_at_speed"][s, 0, nd], rtol=1e-12)


def test_speed_model_varies_smoothly(speed_model):
    """Natural cubic spline in Omega^2 (the contract's interpolation) through every other
    speed predicts the left-out speeds: frequencies to 1e-6, tip shapes to 1e-3 of their size
    (a sign or phase jump between speeds would break this)."""
    m, e = speed_model, speed_model.extra
    x = e["speed_rad_s"] ** 2
    fam1 = m.family == 0
    for key, tol in (("freq_hz_at_speed", 2e-5), ("tip_shapes_at_speed", 2e-3)):
        y = e[key][:, fam1]
        y = y**2 if key.startswith("freq") else y.reshape(y.shape[0], y.shape[1], -1)
        spl = CubicSpline(x[::2], y[::2], bc_type="natural", axis=0)
        err = np.abs(spl(x[1::2]) - y[1::2])
        size = np.abs(y).max(axis=(0, 2)) if y.ndim == 3 else np.abs(y).max(axis=0)
        rel = err / (size[None, :, None] if y.ndim == 3 else size[None, :])
        assert rel.max() < tol, (key, rel.max())


@pytest.mark.parametrize("model, problem", [
    (dict(centrifugal=1), "must be true or false"),
    (dict(centrifugal=True, centrifugal_speeds=1), "centrifugal_speeds must be an integer in [2, 64]"),
    (dict(centrifugal=True, centrifugal_speeds=65), "centrifugal_speeds must be an integer in [2, 64]"),
    (dict(centrifugal=True, centrifugal_max_rpm=3000.0), "must cover the speed profile's top speed 4000"),
    (dict(centrifugal=True, source="my.npz"), "applies to the built-in model only"),
], ids=["bool", "speeds-low", "speeds-high", "max-rpm", "file"])
def test_scenario_option_is_validated(model, problem):
    with pytest.raises(ScenarioError, match=None) as info:
        S.Scenario(model=S.Model(**model))
    assert problem in str(info.value) and "\n" not in str(info.value)


def test_option_off_is_not_written_and_on_round_trips():
    import tomllib
    assert "centrifugal" not in S.dumps_toml(S.Scenario())
    assert "centrifugal = false" in S.default_toml()
    on = S.Scenario(model=S.Model(centrifugal=True, centrifugal_speeds=5, centrifugal_max_rpm=5000.0))
    assert S.scenario_from_dict(tomllib.loads(S.dumps_toml(on))) == on


def test_tracking_follows_veerings_between_distant_speeds(disk, monkeypatch):
    """Up to 20,000 rpm the higher families veer; tracking from 0 straight to 20,000 rpm (the
    interval halved where the MAC drops below MAC_REFINE) follows every branch as tracking
    through 81 speeds does, where one unrefined step picks a wrong mode (150 Hz off)."""
    import bttsim_stream.model.centrifugal as cf
    d, sec, cent, zero = disk
    Omega = 2.0 * np.pi * 20000.0 / 60.0
    fine = solve_cyclic_speeds(d, sec, cent, np.linspace(0.0, Omega, 81), zero)
    coarse = solve_cyclic_speeds(d, sec, cent, np.array([0.0, Omega]), zero)
    np.testing.assert_allclose(coarse.solutions[-1].freq_hz, fine.solutions[-1].freq_hz, rtol=1e-7)
    assert coarse.min_mac > 0.98
    monkeypatch.setattr(cf, "MAC_REFINE", 0.0)
    blind = solve_cyclic_speeds(d, sec, cent, np.array([0.0, Omega]), zero)
    assert np.abs(blind.solutions[-1].freq_hz - fine.solutions[-1].freq_hz).max() > 100.0


@pytest.mark.parametrize("kind", ["mistuned", "asymmetric"])
def test_mistuned_wheel_at_speed_equals_direct_full_wheel_solve(kind):
    """2 % random blade stiffness mistuning, or the asymmetric disk (its ND pairs but 1 and 14
    stay degenerate: their orientation is kept by a Procrustes rotation): the full wheel's own
    prestress (its static solve) and the modes at speed (Ritz on the zero-speed modes and
    their static corrections, tracked) against a direct shift-invert solve at 3600 rpm."""
    import scipy.sparse.linalg as spla
    from bttsim_stream.model.centrifugal import full_wheel_centrifugal
    from bttsim_stream.model.modal_model import DISK_ASYMMETRY
    d = BladedDiskDesign()
    ones = np.ones(d.n_blades)
    if kind == "mistuned":
        kf = 1 + 0.02 * np.random.default_rng(0).standard_normal(d.n_blades)
    else:
        kf, d = ones, replace(d, asymmetry=DISK_ASYMMETRY)
    sp = speed_grid(3600.0 * np.pi / 30.0, 4)
    m = build_model(design=d, stiffness_factors=kf, mass_factors=ones, speed_rad_s=sp)
    zero = build_model(design=d, stiffness_factors=kf, mass_factors=ones)
    assert np.array_equal(m.extra["tip_shapes_at_speed"][0], zero.tip_shapes)
    from bttsim_stream.model.bladed_disk import asymmetry_pattern
    K, M, sectors = assemble_full_wheel(d, kf, ones, asymmetry_pattern(d))
    G, _ = full_wheel_centrifugal(sectors, K)
    w = sp[-1]
    w2 = spla.eigsh(K + w * w * G, k=m.n_modes, M=M, sigma=-1.0, which="LM", tol=1e-13, v0=np.ones(K.shape[0]),
                    return_eigenvectors=False)
    direct = np.sort(np.sqrt(w2) / (2 * np.pi))
    got = np.sort(m.extra["freq_hz_at_speed"][-1])
    np.testing.assert_allclose(got[:2 * d.n_blades], direct[:2 * d.n_blades], rtol=1e-9)  # families 1-2
    np.testing.assert_allclose(got, direct, rtol=1e-5)
    assert m.meta["provenance"]["centrifugal"]["tracking_min_mac"] > 0.99
    # smooth: the tip shapes of family 1 move by little between consecutive speeds
    U = m.extra["tip_shapes_at_speed"][:, m.family == 0].reshape(sp.size, -1, d.n_blades * d.n_tip_nodes * 3)
    cos = np.sum(U[1:] * U[:-1], axis=2) / np.linalg.norm(U[1:], axis=2) / np.linalg.norm(U[:-1], axis=2)
    assert cos.min() > 0.95, cos.min()
    if kind == "asymmetric":
        return
    # a tuned wheel's full-wheel prestress is the cyclic one
    Kt, _, st = assemble_full_wheel(d)
    Gt, _ = full_wheel_centrifugal(st, Kt)
    sec = assemble_sector(d)
    Gc = assemble_full_wheel_speed(d, sec, centrifugal_sector(sec, d.n_blades))
    assert abs(Gt - Gc).max() < 1e-10 * abs(Gc).max()
