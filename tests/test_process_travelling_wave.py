"""Travelling-wave spectra and nodal diameter identification (Fig. 10, Sec. 3.3.2 and 3.3.4)."""

import numpy as np
import pytest

from bttsim_stream.process import (ProcessOptions, TravellingWaveSpectra, fit_revolutions, fit_spectra, identify_nd,
                                   probe_spectra, process_arrays, signed_nd)
from bttsim_stream.paper.validate_processing import simulate

PROBES = np.deg2rad([5.0, 15.15, 23.82, 220.0, 301.5])
NB, EO = 29, 8
WINDOW = {"speed": {"start_rpm": 2450.0, "segments": [{"duration_s": 10.0, "end_rpm": 2700.0}]}}


def _wave(nd, amp_pkpk=2e-3, n_rev=3, c=0.4):
    """Displacements of the Eq. 7 phasing ``sin(EO phi + 2 pi b nd / N + c)`` as the probes see it
    (blade ``b`` reaches probe ``j`` at rotor angle ``theta_j - 2 pi b / N``)."""
    b = np.arange(NB)[:, None]
    phi = PROBES[None, :] - 2 * np.pi * b / NB
    d = 0.5 * amp_pkpk * np.sin(EO * phi + 2 * np.pi * b * nd / NB + c)
    return np.broadcast_to(d, (n_rev, NB, 5)).copy()


@pytest.mark.parametrize("nd", [1, 14, 28, 15, 0, 8, 5], ids=lambda k: f"ND{k}")
def test_fit_spectrum_identifies_the_signed_nd(nd):
    d = _wave(nd)
    f = fit_revolutions(d, PROBES, EO)
    tw = fit_spectra(f.phasor[..., 0], EO)
    expect = int(signed_nd(nd, NB))
    assert identify_nd(tw) == expect
    assert np.all(tw.dominant_nd == expect)
    # magnitude by signed ND (ND 0 is a standing pattern, reported in both directions)
    mags = {k: tw.forward_m[0, k] for k in range(tw.n_nd)}
    mags.update({-k: tw.backward_m[0, k] for k in range(1, tw.n_nd)})
    assert mags[expect] == pytest.approx(2e-3, rel=1e-12)
    assert max(v for k, v in mags.items() if k != expect) < 1e-15


@pytest.mark.parametrize("nd,image", [(1, -14), (14, 2), (-3, -10)], ids=["ND1", "ND14", "ND-3"])
def test_probe_spectrum_shows_the_wave_and_its_image(nd, image):
    d = _wave(nd % NB)
    tw = probe_spectra(d, EO)
    assert tw.forward_m.shape == (3, 5, NB // 2 + 1)

    def mag(k):
        return tw.forward_m[..., k] if k >= 0 else tw.backward_m[..., -k]

    np.testing.assert_allclose(mag(nd), 2e-3, rtol=1e-12)
    np.testing.assert_allclose(mag(image), 2e-3, rtol=1e-12)  # one probe cannot tell them apart
    assert int(signed_nd(2 * EO - nd, NB)) == image


def test_missing_blades_in_spectra():
    d = _wave(1)
    d[0, 4, :] = np.nan
    d[0, 9, 2] = np.nan
    tw = probe_spectra(d, EO)
    assert np.all(np.isfinite(tw.forward_m))
    f = fit_revolutions(d, PROBES, EO)
    fs = fit_spectra(f.phasor[..., 0], EO)
    assert identify_nd(fs) == 1 and fs.forward_m[0, 1] == pytest.approx(2e-3, rel=1e-12)


@pytest.mark.parametrize("excited,expected", [(1, 1), (14, 14)], ids=["ND1", "ND14"])
def test_simulated_run_identifies_the_excited_nd(excited, expected):
    run = simulate(None if excited == 1 else {"excitation": [{"engine_order": 8, "nodal_diameter": excited}]})
    res = process_arrays(run.opr_s, run.toa_s, run.info, ProcessOptions())
    assert res.summary["nd"] == expected
    # at the resonance the wave dominates every revolution's fit spectrum
    assert np.all(res.fit_tw.dominant_nd[res.resonance_revolutions] == expected)
    # probe 1's view (Fig. 10) holds the wave at the same magnitude as the fits
    i = int(np.argmax(np.nanmean(res.fit.amp_pkpk_m[..., 0], axis=1)))
    assert res.probe_tw.forward_m[i, 0, expected] == pytest.approx(res.fit_tw.forward_m[i, expected], rel=0.05)


def test_backward_excitation_is_identified_backward():
    run = simulate(dict(WINDOW, excitation=[{"engine_order": 8, "nodal_diameter": 28}]))
    res = process_arrays(run.opr_s, run.toa_s, run.info, ProcessOptions(calibration=None, prep=False))
    assert res.summary["nd"] == -1


def test_dominant_nd_of_one_spectrum_equals_the_whole_array_rule():
    """One revolution's spectrum (1-D) takes a shortcut when every value is finite: the same
    signed ND as row by row of a 2-D array, with ties (forward wins, the first ND wins), NaN
    and infinities."""
    rng = np.random.default_rng(11)
    rows = rng.random((400, 2, 15)).round(1)  # rounding: many ties
    rows[::7, 0, 3] = np.nan
    rows[::11, 1, :] = np.nan
    rows[::13, 1, 4] = np.inf
    rows[::17, 0, 2] = np.inf
    rows[::19] = rows[::19, ::-1]  # a backward copy of the forward: ties across the directions
    both = TravellingWaveSpectra(rows[:, 0], rows[:, 1], 29)
    whole = both.dominant_nd
    # reference: the rule spelled out (NaN the smallest, forward first on a tie)
    for k, (f, b) in enumerate(rows):
        f2, b2 = np.where(np.isnan(f), -np.inf, f), np.where(np.isnan(b), -np.inf, b)
        i_f, i_b = int(np.argmax(f2)), int(np.argmax(b2))
        want = -i_b if b2[i_b] > f2[i_f] else i_f
        one = TravellingWaveSpectra(f, b, 29).dominant_nd
        assert int(one) == want == int(whole[k])
        assert one.shape == () and one.dtype == whole.dtype
