"""The full result in scratch files (``process_arrays(..., scratch=True)``, what ``bttsim export``
reads by blocks) is the whole-array result, element for element."""

import json
from types import SimpleNamespace

import numpy as np
import pytest

from bttsim_stream.process import fit as fitting, scratch_result, travelling_wave
from bttsim_stream.process.displacement import Geometry
from bttsim_stream.process.history import ScratchRows
from bttsim_stream.process.pipeline import ProcessOptions, process_arrays
from bttsim_stream.process.span_fits import fit_rows, fit_spans

PROBES = np.deg2rad([5.0, 15.15, 23.82, 220.0, 301.5])
NB = 13
FIT_FIELDS = ("coeffs", "amp_pkpk_m", "phase_rad", "amp_std_m", "dc_m", "residual_rms_m", "n_samples")


def _run(n_rev: int, seed: int = 3):
    """A run-up's OPR times and TOAs with a slow vibration and a few missing pulses (its EO 3
    and EO 5 fits show crossings)."""
    rng = np.random.default_rng(seed)
    omega = np.linspace(150.0, 300.0, n_rev)
    opr = np.concatenate([[0.0], np.cumsum(2 * np.pi / omega[:-1])])
    geo = Geometry(n_blades=NB, probe_angles_rad=PROBES, tip_radius_m=0.2)
    toa = opr[:, None, None] + geo.nominal_arrival_angles()[None] / omega[:, None, None]
    toa += 1e-6 * np.sin(np.arange(n_rev) / 40.0)[:, None, None] * rng.uniform(0.5, 1.5, (1, NB, PROBES.size))
    toa += rng.normal(0.0, 2e-8, toa.shape)
    toa[rng.random(toa.shape) < 0.002] = np.nan
    return opr, toa, geo


def _same(a, b) -> bool:
    a = a[:] if isinstance(a, ScratchRows) else np.asarray(a)
    return a.shape == np.shape(b) and a.dtype == np.asarray(b).dtype and np.array_equal(a, b, equal_nan=True)


@pytest.mark.parametrize("options", [dict(engine_orders=(3,)), dict(engine_orders=(3, 5), calibration=None),
                                     dict(eo_range=(2, 5)), dict(engine_orders=(3,), prep=False),
                                     dict(engine_orders=(3,), sampling_angles=False),
                                     dict(engine_orders=(3,), method="sdof"),
                                     dict(engine_orders=(3,), expected_times="exact")],
                         ids=["eo3", "joint-nominal", "scan", "no-prep", "probe-angles", "sdof", "exact"])
def test_scratch_result_is_the_whole_result(options, monkeypatch):
    """Every array of the full result, read back from its scratch files (by rows, with blocks
    of a few dozen revolutions that cut the crossings), is the whole array, and the report
    is the same number for number; the input is left intact."""
    opr, toa, geo = _run(900)
    kept = toa.copy()
    opts = ProcessOptions(**options)
    truth = SimpleNamespace(t_exp_s=np.nan_to_num(toa, nan=0.0) + 1e-7) if opts.expected_times == "exact" else None
    whole = process_arrays(opr, toa, geo, opts, truth=truth)
    monkeypatch.setattr(scratch_result, "SCRATCH_BLOCK", 100)
    monkeypatch.setattr(fitting, "FIT_CHUNK", 37)
    monkeypatch.setattr(travelling_wave, "SPECTRA_CHUNK", 29)
    rows = process_arrays(opr, toa, geo, opts, truth=truth, scratch=True)
    assert np.array_equal(toa, kept, equal_nan=True)
    assert whole.crossings or opts.expected_times == "exact"  # (the fake exact times hide the vibration)
    assert json.dumps(rows.summary, sort_keys=True) == json.dumps(whole.summary, sort_keys=True)
    assert isinstance(rows.displacements.d_m, ScratchRows) and isinstance(rows.fit.coeffs, ScratchRows)
    assert _same(rows.displacements.d_m, whole.displacements.d_m)
    t_exp = whole.displacements.t_exp_s
    for a, b in ((0, 900), (0, 1), (317, 655), (899, 900)):
        assert _same(rows.displacements.t_exp_at(slice(a, b)), t_exp[a:b])
    for name in FIT_FIELDS + ("omega_rad_s", "freq_hz"):
        assert _same(getattr(rows.fit, name), getattr(whole.fit, name)), name
    assert rows.fit.cn == whole.fit.cn and rows.fit.engine_orders == whole.fit.engine_orders
    for tw in ("probe_tw", "fit_tw"):
        a, b = getattr(rows, tw), getattr(whole, tw)
        assert _same(a.forward_m, b.forward_m) and _same(a.backward_m, b.backward_m), tw
    assert np.array_equal(rows.resonance_revolutions, whole.resonance_revolutions)
    if opts.prep:  # the prepared displacements by rows: the whole array's
        assert _same(rows.prepared.d_m[0:900], whole.prepared.d_m)
        assert _same(rows.prepared.offset_m[:], whole.prepared.offset_m)


def test_scratch_needs_one_revolution_per_fit():
    """A fit over several revolutions reads its neighbours: the result stays whole arrays."""
    opr, toa, geo = _run(300)
    opts = ProcessOptions(engine_orders=(3,), window=5)
    rows = process_arrays(opr, toa, geo, opts, scratch=True)
    whole = process_arrays(opr, toa, geo, opts)
    assert isinstance(rows.fit.coeffs, np.ndarray) and _same(rows.fit.coeffs, whole.fit.coeffs)
    assert _same(rows.probe_tw.forward_m, whole.probe_tw.forward_m)


@pytest.mark.parametrize("a, b", [(0, 300), (0, 37), (40, 41), (55, 260), (120, 121), (299, 300), (10, 10)])
def test_fit_rows_are_the_spans_fits(a, b):
    """:func:`fit_rows` of any stretch gives, row for row, :func:`fit_spans`' numbers: the
    sampling angles inside the spans (cut at the stretch's ends), the probe angles elsewhere."""
    opr, toa, geo = _run(300)
    d = np.diff(toa, axis=0, prepend=toa[:1]) * 1e3
    omega = np.linspace(150.0, 300.0, 300)
    spans = [(40, 90), (120, 121), (250, 300)]
    whole = fit_spans(d, PROBES, (3, 5), True, omega, 1, 0.2, spans)
    got = list(fit_rows(d, a, b, PROBES, (3, 5), True, omega, 0.2, spans))
    assert [lo for lo, _, _ in got] == sorted(lo for lo, _, _ in got)
    assert sum(hi - lo for lo, hi, _ in got) == b - a
    for lo, hi, f in got:
        for name in FIT_FIELDS:
            assert _same(getattr(f, name), getattr(whole, name)[lo:hi]), (lo, hi, name)
