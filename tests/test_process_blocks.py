"""Bounded memory: the whole-run steps done in blocks give the numbers of the whole arrays,
and a recording's revolutions are regrouped into arrays as the bus's assembler does."""

from types import SimpleNamespace

import numpy as np
import pytest

from bttsim_stream.bus.stream import RevolutionAssembler
from bttsim_stream import offline
from bttsim_stream.offline import _Acquisition
from bttsim_stream.process import displacement, fit, prep, smoothing, travelling_wave
from bttsim_stream.process.displacement import Geometry, compute_displacements, expected_times
from bttsim_stream.process.history import ScratchRows

PROBES = np.deg2rad([5.0, 15.15, 23.82, 220.0, 301.5])
NB = 13


def _run(n_rev: int, seed: int = 1):
    """A run-up's OPR times and TOAs with vibration, a few missing pulses."""
    rng = np.random.default_rng(seed)
    omega = np.linspace(150.0, 300.0, n_rev)
    opr = np.concatenate([[0.0], np.cumsum(2 * np.pi / omega[:-1])])
    geo = Geometry(n_blades=NB, probe_angles_rad=PROBES, tip_radius_m=0.2)
    psi = geo.nominal_arrival_angles()
    toa = opr[:, None, None] + psi[None] / omega[:, None, None]
    toa += 1e-6 * np.sin(np.arange(n_rev) / 40.0)[:, None, None] * rng.uniform(0.5, 1.5, (1, NB, PROBES.size))
    toa += rng.normal(0.0, 2e-8, toa.shape)
    toa[rng.random(toa.shape) < 0.002] = np.nan
    return opr, toa, geo, omega


def _same(a, b) -> bool:
    return a.shape == b.shape and np.array_equal(a, b, equal_nan=True)


def test_blocks_give_the_whole_arrays_numbers(monkeypatch):
    opr, toa, geo, omega = _run(700)
    whole = compute_displacements(opr, toa, geo, calibration=64)
    d = whole.d_m
    fits = [fit.fit_revolutions(d, PROBES, eos, omega_rad_s=omega, tip_radius_m=r)
            for eos in ((3,), (3, 5)) for r in (None, 0.2)]
    probe_tw, fit_tw = travelling_wave.probe_spectra(d, 3), travelling_wave.fit_spectra(fits[0].phasor[..., 0], 3)
    half = np.clip(3.0 + 6.0 * np.arange(700) / 700, 1, 40)
    prepared = prep.prepare(d, omega, PROBES, (3,), region=prep.locate_resonance(d, PROBES, (3,)), half_width=half)
    # the same with blocks of a few dozen revolutions (and columns)
    for mod, name in ((fit, "FIT_CHUNK"), (displacement, "DISPLACEMENT_CHUNK"), (travelling_wave, "SPECTRA_CHUNK")):
        monkeypatch.setattr(mod, name, 64)
    monkeypatch.setattr(prep, "PREP_BLOCK", 700 * 7)
    monkeypatch.setattr(smoothing, "SMOOTH_BLOCK", 700 * 7)
    blocked = compute_displacements(opr, toa, geo, calibration=64)
    assert _same(blocked.d_m, d)
    assert _same(blocked.t_exp_s, whole.phase.opr_s[:, None, None] + displacement.displacements_from_phase(
        whole.phase, toa, whole.arrival_angles_rad, 0.2)[1])
    assert _same(blocked.t_exp_s, expected_times(whole.phase, whole.arrival_angles_rad, toa))
    k = 0
    for eos in ((3,), (3, 5)):
        for r in (None, 0.2):
            f = fit.fit_revolutions(d, PROBES, eos, omega_rad_s=omega, tip_radius_m=r)
            for name in ("coeffs", "amp_pkpk_m", "phase_rad", "amp_std_m", "dc_m", "residual_rms_m", "n_samples",
                         "freq_hz"):
                assert _same(getattr(f, name), getattr(fits[k], name)), (eos, r, name)
            k += 1
    tw = travelling_wave.probe_spectra(d, 3), travelling_wave.fit_spectra(fits[0].phasor[..., 0], 3)
    for a, b in zip(tw, (probe_tw, fit_tw)):
        assert _same(a.forward_m, b.forward_m) and _same(a.backward_m, b.backward_m)
    p2 = prep.prepare(d, omega, PROBES, (3,), region=prep.locate_resonance(d, PROBES, (3,)), half_width=half)
    assert _same(p2.d_m, prepared.d_m) and _same(p2.offset_m, prepared.offset_m)
    assert not np.allclose(np.nan_to_num(p2.offset_m), 0.0)  # a baseline was removed, smoothing done


def test_displacement_rows_are_the_whole_arrays_rows(monkeypatch):
    """The first pass's displacements computed when asked for (rows, blocks of blades; OPR
    model or exact times) are the rows and columns of :func:`compute_displacements`'s, and
    the pipeline's column medians on blocks of blades are the whole array's."""
    from bttsim_stream.process.pipeline import _column_median

    opr, toa, geo, _ = _run(700)
    t_exp = toa + 1e-7
    for t in (None, t_exp):
        whole = compute_displacements(opr, toa, geo, t_exp_s=t, calibration=None).d_m
        rows = displacement.first_pass_rows(opr, toa, geo, t_exp_s=t)
        assert rows.shape == whole.shape
        assert _same(rows[0:700], whole) and _same(rows[123:456], whole[123:456])
        assert _same(rows.blades(slice(3, 8)), whole[:, 3:8])
        monkeypatch.setattr(displacement, "DISPLACEMENT_CHUNK", 64)  # blades computed in blocks of revolutions
        assert _same(rows.blades(slice(0, NB)), whole)
        monkeypatch.setattr(prep, "PREP_BLOCK", 700 * 5 * 2)  # medians on two blades at a time
        monkeypatch.setattr("bttsim_stream.process.pipeline.PREP_BLOCK", 700 * 5 * 2)
        with np.errstate(all="ignore"):
            want = np.nanmedian(whole, axis=0)
        assert _same(_column_median(rows), np.where(np.isfinite(want), want, 0.0))
        monkeypatch.undo()


@pytest.mark.parametrize("remove_offset", [True, False])
def test_prepared_rows_are_the_whole_arrays_rows(monkeypatch, remove_offset):
    """``prepare(..., rows_only=True)`` prepares the revolutions asked for: in any slices, in
    any order, over several smoother blocks, with missing samples, the rows of the whole
    prepared array."""
    opr, toa, geo, omega = _run(700)
    d = compute_displacements(opr, toa, geo, calibration=64).d_m
    assert np.isnan(d).any()
    half = np.clip(3.0 + 6.0 * np.arange(700) / 700, 1, 40)
    opts = prep.PrepOptions(remove_offset=remove_offset)
    region = prep.locate_resonance(d, PROBES, (3,))
    monkeypatch.setattr(smoothing, "SMOOTH_BLOCK", 64 * NB * PROBES.size)  # smoother blocks of 64 revolutions
    whole = prep.prepare(d, omega, PROBES, (3,), opts, region=region, half_width=half)
    lazy = prep.prepare(d, omega, PROBES, (3,), opts, region=region, half_width=half, rows_only=True)
    assert isinstance(lazy.d_m, prep.PreparedRows) and lazy.d_m.shape == d.shape
    for a, b in ((0, 700), (650, 700), (0, 1), (63, 65), (100, 611), (5, 6), (0, 700)):
        assert _same(lazy.d_m[a:b], whole.d_m[a:b]), (a, b)
    assert _same(np.concatenate([lazy.d_m[a:a + 50] for a in range(0, 700, 50)]), whole.d_m)
    assert _same(lazy.offset_m[:], whole.offset_m)


def _msg(kind, rev, value, probe=0):
    header = SimpleNamespace(revolution=rev)
    body = SimpleNamespace(opr_s=value) if kind == "opr" else SimpleNamespace(probe=probe, toa_s=value)
    return kind, SimpleNamespace(header=header, body=body)


@pytest.mark.parametrize("scratch", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recording_regrouped_as_the_assembler_does(seed, scratch, monkeypatch):
    """Shuffled fragments with duplicates, lost batches, OPR-less revolutions and bad ones:
    the complete revolutions of ``RevolutionAssembler.pop(final=True)``, in order; also with
    the TOAs in a scratch file and 8 revolutions in memory (late batches and duplicates of
    rows already written to the file)."""
    monkeypatch.setattr(offline, "_WINDOW", 8)
    rng = np.random.default_rng(seed)
    nb, npr, n = 4, 3, 60
    msgs = []
    for r in range(n):
        if rng.random() > 0.05:
            msgs.append(_msg("opr", r, 0.01 * r + rng.normal(0, 1e-4)))
        for p in range(npr):
            if rng.random() > 0.03:
                msgs.append(_msg("toa", r, rng.normal(size=nb), p))
    msgs += [msgs[i] for i in rng.integers(0, len(msgs), 25)]  # repeats: the first one stays
    msgs += [_msg("toa", 3, rng.normal(size=nb), 1), _msg("opr", 5, 99.0)]  # later duplicates, other values
    msgs += [_msg("toa", 7, rng.normal(size=nb + 1), 0), _msg("toa", 8, rng.normal(size=nb), npr),
             _msg("opr", -1, 0.0), _msg("opr", 9, np.inf)]  # refused
    order = rng.permutation(len(msgs) - 6)  # the duplicates and refused ones last
    msgs = [msgs[i] for i in order] + msgs[-6:]
    asm, acq = RevolutionAssembler(nb, npr), _Acquisition(nb, npr, 16, scratch=scratch)  # a small capacity: it grows
    for kind, d in msgs:
        asm.add(kind, d)
        acq.add(kind, d)
    want = [r for r in asm.pop(final=True) if r.complete]
    numbers, opr, toa = acq.complete()
    assert isinstance(toa, ScratchRows) == scratch
    toa = toa[:]
    assert numbers.tolist() == [r.revolution for r in want]
    assert _same(opr, np.array([r.opr_s for r in want]))
    assert _same(toa, np.stack([r.toa_s for r in want]))
    assert acq.ignored == asm.ignored == 4
    assert acq.duplicates == asm.duplicates


@pytest.mark.parametrize("options", [dict(engine_orders=(3,)), dict(engine_orders=(3,), method="sdof"),
                                     dict(engine_orders=(3, 5), calibration=None), dict(engine_orders=(3,), window=5),
                                     dict(eo_range=(2, 5)), dict(engine_orders=(3,), prep=False),
                                     dict(engine_orders=(3,), expected_times="exact")])
def test_report_only_is_the_same_report(options):
    """``spectra=False`` (``bttsim process``, the processor's final report) leaves out the
    run's spectra, the TOAs past Eq. 1, the prepared displacements and the first pass's
    amplitudes (freed after the report's fits), the whole baseline array (evaluated by rows),
    the displacements in memory (in scratch files) and the fits' arrays the report does not
    read, and nothing else: the same report,
    number for number, the same fits and offsets, and the input intact."""
    import json

    from bttsim_stream.process.pipeline import ProcessOptions, process_arrays

    opr, toa, geo, omega = _run(900, seed=3)
    kept = toa.copy()
    opts = ProcessOptions(**options)
    truth = SimpleNamespace(t_exp_s=np.nan_to_num(toa, nan=0.0) + 1e-7) if opts.expected_times == "exact" else None
    full = process_arrays(opr, toa, geo, opts, truth=truth)
    only = process_arrays(opr, toa, geo, opts, truth=truth, spectra=False)
    assert only.probe_tw is None and only.fit_tw is None and only.displacements.toa_s is None
    assert full.probe_tw.forward_m.shape == (900, PROBES.size, NB // 2 + 1)
    assert json.dumps(only.summary, sort_keys=True) == json.dumps(full.summary, sort_keys=True)
    if opts.prep:
        assert only.prepared.d_m is None and full.prepared.d_m.shape == toa.shape
        assert _same(only.prepared.offset_m[:], full.prepared.offset_m)  # a Baseline, or zeros: by rows
    else:
        assert only.prepared is None and full.prepared is None
    # one revolution per fit: the displacements are not held but read back from scratch files
    assert isinstance(only.displacements.d_m, ScratchRows) == (opts.window == 1)
    assert _same(only.displacements.d_m[:], full.displacements.d_m)
    assert _same(only.fit.freq_hz, full.fit.freq_hz)
    for name in ("coeffs", "amp_pkpk_m", "phase_rad"):
        a, b = getattr(only.fit, name), getattr(full.fit, name)
        if opts.window > 1:
            assert _same(a, b), name
            continue
        # one revolution per fit: held on the revolutions the report reads, NaN elsewhere
        held = a.held()
        assert a.shape == b.shape and _same(a[held], b[held]) and np.isnan(a[~held]).all(), name
        assert all(held[c.lo:c.hi + 1].all() for c in only.crossings)  # a dwell's are fitted again
    assert (only.fit.n_samples is None) == (opts.window == 1)
    assert _same(toa, kept)


def test_report_only_fits_the_zeroing_skirt_again_by_blocks(monkeypatch):
    """The zeroing correction's skirt (from the reference to the crossing: as long as the run
    between them) is not held with the report's fits but fitted again when the correction
    reads it, by blocks: the same report as the whole run's fits give, and none of the
    skirt's revolutions held outside the crossings' margins."""
    import json

    from bttsim_stream.process import fit as fitting
    from bttsim_stream.process import zeroing
    from bttsim_stream.process.pipeline import ProcessOptions, process_arrays

    opr, toa, geo, omega = _run(900, seed=3)
    opts = ProcessOptions(engine_orders=(3,))
    full = process_arrays(opr, toa, geo, opts)
    read = []
    gain = zeroing.tail_gain
    monkeypatch.setattr(zeroing, "tail_gain", lambda g, P, block=None: read.append(g.size) or gain(g, P, block))
    monkeypatch.setattr(zeroing, "TAIL_BLOCK", 37)
    monkeypatch.setattr(fitting, "FIT_CHUNK", 29)
    only = process_arrays(opr, toa, geo, opts, spectra=False)
    assert read and min(read) > 37  # a correction was made, over several blocks
    assert json.dumps(only.summary, sort_keys=True) == json.dumps(full.summary, sort_keys=True)
    c = only.crossings[0]
    tail = zeroing.tail_revolutions(only.reference, False, list(only.crossings), full.fit.omega_rad_s, c)[2]
    held = only.fit.coeffs.held()
    assert not held[tail].all() and held[c.lo:c.hi + 1].all()


@pytest.mark.parametrize("options", [dict(engine_orders=(3,)), dict(engine_orders=(3, 5), prep=False)])
def test_report_only_fits_a_dwell_again_by_blocks(options, monkeypatch):
    """A dwell's fits (as long as the dwell) are not held with the report's fits: its means
    fit them again by blocks of revolutions as they read them (the unsmoothed fits too), and
    give the same steady entries as the whole run's fits, number for number."""
    import json

    from bttsim_stream.process import fit as fitting
    from bttsim_stream.process import steady
    from bttsim_stream.process.pipeline import ProcessOptions, process_arrays

    rng = np.random.default_rng(5)
    omega = np.concatenate([np.linspace(150.0, 250.0, 600), np.full(500, 250.0), np.linspace(250.0, 300.0, 300)])
    opr = np.concatenate([[0.0], np.cumsum(2 * np.pi / omega[:-1])])
    geo = Geometry(n_blades=NB, probe_angles_rad=PROBES, tip_radius_m=0.2)
    toa = opr[:, None, None] + geo.nominal_arrival_angles()[None] / omega[:, None, None]
    toa += 1e-6 * np.sin(3 * opr)[:, None, None] * rng.uniform(0.5, 1.5, (1, NB, PROBES.size))
    toa += rng.normal(0.0, 2e-8, toa.shape)
    toa[rng.random(toa.shape) < 0.002] = np.nan
    opts = ProcessOptions(**options)
    full = process_arrays(opr, toa, geo, opts)
    assert full.segments.dwells and full.report.steady
    monkeypatch.setattr(steady, "DWELL_BLOCK", 37)
    monkeypatch.setattr(fitting, "FIT_CHUNK", 29)
    only = process_arrays(opr, toa, geo, opts, spectra=False)
    assert json.dumps(only.summary, sort_keys=True) == json.dumps(full.summary, sort_keys=True)
    dw = only.segments.dwells[0]
    held = only.fit.coeffs.held()
    assert not held[dw.start:dw.stop].all()


@pytest.mark.parametrize("options", [dict(calibration=None), dict()])
def test_report_only_with_dwells_beside_a_crossing(options):
    """A crossing between two dwells (a run-up with a dwell before and after the resonance):
    the readers of a blade's peak at the crossing's edge reach into the dwells' unsmoothed
    fits, which the report alone holds there: the same report as the whole run's fits."""
    import json

    from bttsim_stream.paper.validate_processing import simulate
    from bttsim_stream.process.pipeline import ProcessOptions, process_arrays

    run = simulate({"run": {"seed": 5}, "acquisition": {"probe_angle_error_deg": 0.2, "trigger_jitter_s": 3e-8},
                    "speed": {"start_rpm": 2300.0, "segments": [
                        {"duration_s": 8.0, "end_rpm": 2500.0}, {"duration_s": 6.0, "end_rpm": 2500.0},
                        {"duration_s": 12.0, "end_rpm": 2800.0}, {"duration_s": 6.0, "end_rpm": 2800.0}]}})
    opts = ProcessOptions(**options)
    full = process_arrays(run.opr_s, run.toa_s, run.info, opts, truth=run.truth)
    only = process_arrays(run.opr_s, run.toa_s, run.info, opts, truth=run.truth, spectra=False)
    c = full.crossings[0]
    assert any(dw.stop == c.lo or dw.start == c.hi + 1 for dw in full.segments.dwells)
    assert json.dumps(only.summary, sort_keys=True) == json.dumps(full.summary, sort_keys=True)
