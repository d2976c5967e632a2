"""Rerun views: Eq. 1 and layout as the views use them, bulk logging of a recording, live
feeding, the viewer node, and the web viewer (browser)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
import warnings
from collections import deque
from itertools import combinations
from pathlib import Path

import numpy as np
import pytest

from _procs import start as _start, stop as _stop
from bttsim_stream.acquisition import AcquisitionStream
from bttsim_stream.bus import codec, keys
from bttsim_stream.bus.recording import McapRecorder, read_recording
from bttsim_stream.bus.session import free_port
from bttsim_stream.bus.stream import Sequencer
from bttsim_stream.errors import BttsimError
from bttsim_stream.offline import with_processing
from bttsim_stream.process.results import RevolutionFit
from bttsim_stream.process.resonance import ResonancePeaks, ResonanceReport, TruthPeaks
from bttsim_stream.scenario import load_scenario

rr = pytest.importorskip("rerun")
from rerun.chunk import RrdReader  # noqa: E402

from bttsim_stream import views  # noqa: E402
from bttsim_stream.views import paths  # noqa: E402
from bttsim_stream.views._plot2d import BOUNDS, Label, PlotFrame, label_box, place_labels  # noqa: E402
from bttsim_stream.views.campbell import CampbellLayout, frequency_span_text  # noqa: E402
from bttsim_stream.views.resonance import resonance_markdown  # noqa: E402
from bttsim_stream.views._common import turbo  # noqa: E402
from bttsim_stream.views._plot2d import LINE_H, PLOT_HEIGHT  # noqa: E402
from bttsim_stream.views.travelling_wave import GAMMA, colour_ticks, nd_ticks  # noqa: E402
from bttsim_stream.views.revolutions import CALIBRATION_REVOLUTIONS, RevolutionDisplacements  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SHORT = "[speed]\nstart_rpm = 2450.0\nend_rpm = 2700.0\nduration_s = 3.0\n"  # through the resonance (2581.5 rpm)
N_REV = 128  # revolutions of SHORT
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


# --------------------------------------------------------------------------------------
# Fixtures and helpers
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def short_scenario(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("scenario") / "short.toml"
    path.write_text(SHORT)
    return path


@pytest.fixture(scope="module")
def short_run(short_scenario):
    """The acquisition messages of a 3 s run near the ND 1 resonance (127 revolutions,
    with truth), as the simulator publishes them."""
    stream = AcquisitionStream(load_scenario(short_scenario))
    messages = [stream.meta]
    for _, msgs in stream.batches():
        messages += msgs
    return stream, messages


@pytest.fixture(scope="module")
def short_mcap(short_run, tmp_path_factory) -> Path:
    stream, messages = short_run
    out = tmp_path_factory.mktemp("views") / "short.mcap"
    with McapRecorder(out, run_metadata=stream.run_metadata_record) as rec:
        rec.write_all(messages)
    return out


@pytest.fixture(scope="module")
def processed_mcap(short_mcap) -> Path:
    """The short recording with the streaming processor's messages (fits, travelling waves,
    resonance report), as ``bttsim view`` makes it."""
    return Path(with_processing(short_mcap, short_mcap.with_name("processed.mcap")))


def decoded(messages):
    """``[(kind, Decoded)]`` of bus messages."""
    return [(keys.parse_key(m.key).kind, codec.decode_message(m.key, m.payload)) for m in messages]


def show(info, stream, final=True):
    """Feed ``(kind, Decoded)`` OPR/TOA messages to the views' revolution stage one by one;
    ``(revolutions, d_m, shown_after)``: ``shown_after[i]`` is the last revolution shown
    after message ``i`` (-1: none)."""
    stage = RevolutionDisplacements(info)
    revs, d, after = [], [], []
    for kind, msg in stream:
        stage.add(kind, msg)
        out = stage.pop()
        if out is not None:
            revs.append(out.revolution), d.append(out.d_m)
        after.append(int(revs[-1][-1]) if revs else -1)
    out = stage.pop(final=final)
    if out is not None:
        revs.append(out.revolution), d.append(out.d_m)
    return np.concatenate(revs), np.concatenate(d), after


def truth_of(stream) -> dict:
    return {msg.header.revolution: msg.body for kind, msg in stream if kind == "truth"}


def rrd_verify(path: Path) -> None:
    res = subprocess.run([sys.executable, "-m", "rerun", "rrd", "verify", str(path)], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr


def rrd_entities(path: Path) -> dict[str, dict]:
    """``entity path -> {"rows": temporal rows, "static": bool}`` of the recording store."""
    out: dict[str, dict] = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a file still being written has no footer
        for chunk in RrdReader(path).stream():
            e = out.setdefault(chunk.entity_path, {"rows": 0, "static": False})
            if chunk.is_static:
                e["static"] = True
            else:
                e["rows"] += chunk.num_rows
    return out


def static_value(path: Path, entity: str, suffix: str):
    """The last static value of component ``suffix`` (e.g. ``":strips"``) of ``entity``."""
    value = None
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == entity and chunk.is_static:
            batch = chunk.to_record_batch()
            for name in batch.schema.names:
                if name.endswith(suffix):
                    value = batch.column(name).to_pylist()[-1]
    if value is None:
        raise AssertionError(f"{entity}: no static {suffix}")
    return value


def static_tensor(path: Path, entity: str) -> np.ndarray:
    col = static_value(path, entity, ":data")[0]
    buffer = col["buffer"]
    values = buffer[1] if isinstance(buffer, tuple) else buffer
    return np.asarray(values, dtype=np.float32).reshape(col["shape"])


def temporal(path: Path, entity: str, suffix: str) -> tuple[np.ndarray, list]:
    """``(revolution (n,), values)`` of a temporal component, sorted by revolution."""
    revs, values = [], []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == entity and not chunk.is_static:
            batch = chunk.to_record_batch()
            name = next(n for n in batch.schema.names if n.endswith(suffix))
            revs += batch.column("revolution").to_pylist()
            values += batch.column(name).to_pylist()
    order = np.argsort(revs, kind="stable")
    return np.asarray(revs)[order], [values[i] for i in order]


def to_box(path: Path, entity: str, xy: np.ndarray) -> np.ndarray:
    """Data points of a plot (``entity`` holds its Transform3D) in screen box units."""
    scale = np.asarray(static_value(path, entity, ":scale")[0])
    shift = np.asarray(static_value(path, entity, ":translation")[0])
    return xy * scale[:2] + shift[:2]


def rewrite_metadata(src: Path, dst: Path, **changes) -> None:
    """A copy of a recording whose run metadata has ``changes``."""
    recording = read_recording(src)
    with McapRecorder(dst, run_metadata=recording.run_metadata) as out:
        for m in recording.messages:
            if keys.parse_key(m.key).kind == "meta":
                d = codec.decode_run_metadata(m.payload, m.key)
                m = dataclasses.replace(m, payload=codec.encode_run_metadata(
                    d.header, dataclasses.replace(d.body, **changes)))
            out.write_message(m)


# --------------------------------------------------------------------------------------
# Eq. 1 as the views compute it (the processing's rotor phase and Eq. 1)
# --------------------------------------------------------------------------------------


@pytest.mark.unit
def test_views_eq1_is_the_simulators_exact_eq1_one_revolution_late(short_run):
    stream = decoded(short_run[1])
    info, truth = stream[0][1].body, truth_of(stream)
    acq = [(k, m) for k, m in stream if k in ("opr", "toa")]
    revs, d, after = show(info, acq)
    np.testing.assert_array_equal(revs, np.arange(N_REV))
    d_eq1 = np.stack([truth[k].d_eq1_m[0] for k in revs])
    # the sensing angles of the metadata: exact expected times but for rounding, except the
    # last revolution, whose speed is extrapolated (no next OPR pulse)
    np.testing.assert_allclose(d[:-1], d_eq1[:-1], rtol=0, atol=1e-11)
    np.testing.assert_allclose(d[-1], d_eq1[-1], rtol=0, atol=1e-6)
    # revolution k is shown as soon as revolution k + 1 is complete (its OPR and every TOA
    # batch); the first one also waits for revolution 2 (for its acceleration)
    n_probes = info.n_probes
    last_of_rev = [i for i, (k, m) in enumerate(acq) if k == "toa" and m.body.probe == n_probes - 1]
    assert [after[i] for i in last_of_rev] == [-1, -1] + list(range(1, N_REV - 1))


@pytest.mark.unit
@pytest.mark.parametrize("sensing", [True, False], ids=["nominal", "calibrated"])
def test_views_phases_of_many_revolutions_at_once_are_those_of_one_at_a_time(short_run, sensing):
    """Revolutions shown in one batch (one rotor-phase call for all their OPR windows) are bit
    for bit those shown one at a time (a call per revolution), over lost OPR pulses too."""
    stream = decoded(short_run[1])
    info = stream[0][1].body if sensing else dataclasses.replace(stream[0][1].body, sensing_angles_rad=None)
    acq = [(k, m) for k, m in stream if k in ("opr", "toa") and not (k == "opr" and m.header.seq % 11 == 4)]
    one, batch = RevolutionDisplacements(info), RevolutionDisplacements(info)
    rows = []
    for kind, msg in acq:
        one.add(kind, msg)
        batch.add(kind, msg)
        rows.append(one.pop())
    rows.append(one.pop(final=True))
    rows = [r for r in rows if r is not None]
    whole = batch.pop(final=True)
    assert whole.revolution.size > N_REV // 2 and one.skipped == batch.skipped
    for name in ("revolution", "opr_s", "omega_rad_s", "d_m"):
        got = np.concatenate([getattr(r, name) for r in rows])
        assert got.tobytes() == getattr(whole, name).tobytes(), name


@pytest.mark.unit
def test_views_eq1_without_sensing_angles_is_calibrated_on_the_first_revolutions(short_run):
    stream = decoded(short_run[1])
    info = dataclasses.replace(stream[0][1].body, sensing_angles_rad=None)
    truth = truth_of(stream)
    revs, d, after = show(info, [(k, m) for k, m in stream if k in ("opr", "toa")])
    assert revs.size == N_REV and max(after[:50]) == -1  # held back until the calibration
    d_eq1 = np.stack([truth[k].d_eq1_m[0] for k in revs])
    # calibration takes the median arrival over the window as the undeflected one: the
    # window's vibration (this run starts near resonance) becomes the zero
    reference = np.median(d_eq1[:CALIBRATION_REVOLUTIONS], axis=0)
    assert np.abs(reference).max() > 1e-4
    # the calibration shifts an arrival angle, which is the displacement R dpsi only up to the
    # ratio of the revolution's mean to its instantaneous speed (1e-4 in this sweep): 1e-8 m
    np.testing.assert_allclose(d[:-1], (d_eq1 - reference)[:-1], rtol=0, atol=5e-8)


@pytest.mark.unit
def test_views_eq1_over_lost_messages(short_run):
    stream = decoded(short_run[1])
    info, truth = stream[0][1].body, truth_of(stream)
    lost_opr, lost_toa = 40, (60, 2)  # revolution 40's OPR pulse; probe 2's batch of revolution 60
    acq = [(k, m) for k, m in stream if k in ("opr", "toa")
           and not (k == "opr" and m.header.revolution == lost_opr)
           and not (k == "toa" and (m.header.revolution, m.body.probe) == lost_toa)]
    revs, d, _ = show(info, acq)
    np.testing.assert_array_equal(revs, [k for k in range(N_REV) if k != lost_opr])  # no OPR: not placed
    i60 = list(revs).index(60)
    assert np.isnan(d[i60, :, 2]).all() and np.isfinite(np.delete(d[i60], 2, axis=1)).all()
    d_eq1 = np.stack([truth[k].d_eq1_m[0] for k in revs])
    err = np.nanmax(np.abs(d - d_eq1), axis=(1, 2))
    before = list(revs).index(lost_opr - 1)  # no next pulse: extrapolated speed
    assert err[before] < 1e-6
    # after the gap, revolution 41 takes the acceleration of 42 (row 0 of OPR 41, 42, 43)
    assert np.delete(err, [before, -1]).max() < 1e-11


# --------------------------------------------------------------------------------------
# Layout: blueprint, plots, labels, tables
# --------------------------------------------------------------------------------------


def _views_of(container) -> list:
    out = []
    for item in getattr(container, "contents", []):
        out += _views_of(item) if hasattr(item, "kind") else [item]
    return out


@pytest.mark.unit
@pytest.mark.parametrize("n_probes, eos", [(1, (8,)), (5, (8, 16))], ids=["one-probe-one-eo", "five-probes-two-eos"])
def test_blueprint_has_the_views_of_every_probe_and_engine_order(n_probes, eos):
    bp = views.build_blueprint(n_probes, n_blades=29, engine_orders=eos)
    tabs = bp.root_container
    names = [t.name for t in tabs.contents]
    assert names == ["Overview", *[f"Fits EO {e}" for e in eos], "Travelling wave", "Displacement",
                     "Rotor & Campbell", "Resonance"]
    by_tab = {t.name: {(v.class_identifier, v.origin) for v in _views_of(t)} for t in tabs.contents}
    assert by_tab["Travelling wave"] >= {("2D", paths.tw_map_path(j)) for j in range(n_probes)}
    assert ("2D", paths.tw_map_path(n_probes)) not in by_tab["Travelling wave"]
    assert ("2D", paths.tw_map_path(0)) in by_tab["Overview"]
    assert by_tab["Displacement"] == {("TimeSeries", paths.displacement_path(j)) for j in range(n_probes)}
    for e in eos:
        assert by_tab[f"Fits EO {e}"] >= {("TimeSeries", paths.fit_path(e)), ("2D", paths.fit_rpm_path(e)),
                                          ("TimeSeries", f"{paths.fit_path(e)}/phase_deg"),
                                          ("TimeSeries", f"{paths.fit_path(e)}/freq_hz")}
        amplitude = next(v for v in _views_of(tabs.contents[1 + eos.index(e)]) if v.origin == paths.fit_path(e))
        assert f"+ /{paths.TRUTH_AMP}" in amplitude.contents and "+ $origin/amp_pkpk_mm" in amplitude.contents
    # the overview's amplitude is the first EO's plot against speed (the Fits tab's), not against revolution
    assert ("2D", paths.fit_rpm_path(eos[0])) in by_tab["Overview"]
    assert not any(kind == "TimeSeries" and origin.startswith("fit/") for kind, origin in by_tab["Overview"])
    assert by_tab["Rotor & Campbell"] == {("2D", paths.ROTOR), ("2D", paths.CAMPBELL)}


def _run_info(short_run, **changes):
    return dataclasses.replace(short_run[0].info, **changes)


@pytest.mark.unit
@pytest.mark.parametrize("changes", [{}, {"speed_range_rpm": (1000.0, 4000.0)},
                                     {"engine_orders": (8, 16), "nodal_diameters": (1, 3)},
                                     {"family_freq_hz": None, "speed_range_rpm": (300.0, 12000.0)}],
                         ids=["short-run", "default-speeds", "two-eos", "no-families-fast"])
def test_campbell_labels_do_not_overlap(short_run, changes):
    info = _run_info(short_run, **changes)
    lay = CampbellLayout(info)
    frame = PlotFrame(None, paths.CAMPBELL, (0.0, lay.x_top_rpm), (0.0, lay.f_top_hz), x_label=lambda x: f"{x:g} rpm",
                      y_label=lambda f: f"{f:g} Hz")
    lay.place(frame)
    boxes = [label_box(text, *spot) for text, spot, _ in lay.labels]
    for a, b in combinations(boxes + frame.obstacles(), 2):
        assert not (a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]), (a, b)
    assert all(BOUNDS[0] <= b[0] and BOUNDS[1] <= b[1] and b[2] <= BOUNDS[2] and b[3] <= BOUNDS[3] for b in boxes)
    texts = [t for t, _, _ in lay.labels]
    assert all(f"EO {e}" in texts for e in info.engine_orders)  # the excited EOs always
    assert sum(t.startswith("EO ") and " x ND" not in t for t in texts) >= 10
    if not changes:  # the short run: every EO line, the crossing, the run range and the family
        assert texts.count("EO 12") == 1 and "run 2450-2700 rpm" in texts
        assert any(t.startswith("EO 8 x ND 1: ") for t in texts) and any(t.startswith("family 1") for t in texts)
    for t in texts:  # a span whose ends print alike is one value
        if t.startswith("family ") and "-" in t:
            lo, hi = t.split(": ")[1].removesuffix(" Hz").split("-")
            assert lo != hi, t


@pytest.mark.unit
@pytest.mark.parametrize("lo, hi, text", [(343.9, 347.5, "344-348 Hz"), (343.4, 347.4, "343-347 Hz"),
                                          (817.9172, 817.9172, "817.9 Hz"), (817.61, 818.38, "817.6-818.4 Hz"),
                                          (817.91, 817.94, "817.9 Hz")],
                         ids=["family-1", "whole-hz", "one-line", "same-whole-hz", "same-tenth"])
def test_family_frequency_span_is_one_value_when_its_ends_print_alike(lo, hi, text):
    assert frequency_span_text(lo, hi) == text


@pytest.mark.unit
@pytest.mark.parametrize("n_nd, ticks", [(15, [-14, -10, -5, 0, 5, 10, 14]), (4, [-3, -2, -1, 0, 1, 2, 3]),
                                         (2, [-1, 0, 1]), (1, [0])], ids=["29-blades", "7-blades", "3-blades", "1"])
def test_travelling_wave_map_ticks_every_round_nd_and_both_ends(n_nd, ticks):
    np.testing.assert_array_equal(nd_ticks(n_nd), ticks)


@pytest.mark.unit
def test_travelling_wave_colour_bar_ticks_sit_where_their_colour_is():
    ticks = colour_ticks(2.37)
    assert [v for v, _ in ticks][:2] == [0.0, 0.5] and ticks[-1][0] <= 2.37
    for v, h in ticks:  # the bar's colour at height h is the map's colour of v mm
        np.testing.assert_array_equal(turbo(h), turbo((v / 2.37) ** GAMMA))
    heights = np.array([h for _, h in ticks]) * PLOT_HEIGHT
    assert np.all(np.diff(heights) >= LINE_H)  # labels do not overlap


@pytest.mark.unit
def test_turbo_is_close_to_the_turbo_colour_map():
    matplotlib = pytest.importorskip("matplotlib")
    x = np.linspace(0, 1, 257)
    ref = np.round(matplotlib.colormaps["turbo"](x)[:, :3] * 255)
    err = np.abs(turbo(x).astype(int) - ref)
    assert err.mean() < 8 and err.max() <= 32
    assert turbo([np.nan, -1.0, 2.0]).tolist() == turbo([0.0, 0.0, 1.0]).tolist()


@pytest.mark.unit
def test_place_labels_takes_the_first_free_spot_or_leaves_the_label_out():
    first = Label("abc", ((0.5, 0.3),))
    clash = Label("abc", ((0.5, 0.3), (0.5, 0.3 + 0.04), (0.5, 0.45)))
    nowhere = Label("abc", ((0.5, 0.3), (5.0, 5.0)))  # taken, or out of bounds
    assert place_labels([first, clash, nowhere]) == [(0.5, 0.3), (0.5, 0.45), None]
    assert place_labels([first], obstacles=[label_box("x", 0.5, 0.3)]) == [None]


@pytest.mark.unit
def test_plot_frame_maps_data_into_the_box_and_grows_round():
    frame = PlotFrame(None, "plot", None, (0.0, 0.0), x_label=str, y_label=str)
    frame.draw = lambda: None  # no output here: the ranges only
    assert frame.include([2450.0, 2700.0], [0.83])
    x0, x1 = frame.x_range
    assert x0 < 2450.0 and x1 > 2700.0 and x0 % 50 == 0 and x1 % 50 == 0
    assert frame.y_range == (0.0, 1.0)  # 10 % headroom, rounded
    assert not frame.include([2500.0], [0.9])  # already inside
    np.testing.assert_allclose(frame.to_data(*frame.to_box(2555.0, 0.42).T), [2555.0, 0.42])
    fixed = PlotFrame(None, "plot", (0.0, 10.0), (0.0, 2.0), x_label=str, y_label=str)
    fixed.draw = lambda: None
    fixed.include([20.0], [1.0])
    assert fixed.x_range == (0.0, 10.0)  # a given x range stays


def _report(truth: bool) -> ResonanceReport:
    nb = 29
    amp, freq = np.linspace(2.0e-3, 2.4e-3, nb), np.full(nb, 345.123)
    peaks = ResonancePeaks(revolution=np.full(nb, 60.0), amp_pkpk_m=amp, freq_hz=freq,
                           damping_ratio=np.full(nb, np.nan), method="max")
    if not truth:
        return ResonanceReport(nd=-1, eo=8, cn=1.43, peaks=peaks)
    tp = TruthPeaks(revolution=np.full(nb, 61), amp_pkpk_m=amp * 1.01, freq_hz=freq * 1.0001)
    return ResonanceReport(nd=1, eo=8, cn=1.43, peaks=peaks, truth=tp, e_a_pct=np.full(nb, 0.99),
                           e_f_pct=np.full(nb, 0.01))


@pytest.mark.unit
@pytest.mark.parametrize("truth", [True, False], ids=["with-truth", "blind"])
def test_resonance_tables_are_narrow(truth):
    text = resonance_markdown(_report(truth))
    rows = [line for line in text.splitlines() if line.startswith("|")]
    assert len(rows) == (2 * (2 + 29) if truth else 2 + 29)
    assert max(line.count("|") - 1 for line in rows) == (4 if truth else 3)
    assert max(len(line) for line in rows) <= 40
    assert "| 28 | 2.4000 | 2.4240 | 0.990 |" in rows if truth else "| 28 | 2.4000 | 345.123 |" in rows
    assert ("ND 1 (forward)" if truth else "ND -1 (backward)") in text


# --------------------------------------------------------------------------------------
# Recordings
# --------------------------------------------------------------------------------------


@pytest.mark.integration
def test_log_recording_of_a_raw_acquisition(short_mcap, tmp_path):
    out = tmp_path / "raw.rrd"
    session = views.log_recording(short_mcap, out)
    assert session.sinks.rrd_path == str(out) and session.stats["revolutions"] == N_REV
    assert session.stats["bad"] == 0 and session.stats["fits"] == 0 and session.stats["truth"] == N_REV
    rrd_verify(out)
    ent = rrd_entities(out)
    for probe in range(5):
        assert ent[f"/{paths.displacement_path(probe)}/btt"]["rows"] == N_REV
        assert ent[f"/{paths.displacement_path(probe)}/d_eqv"]["rows"] == N_REV
    for path in (paths.SPEED, paths.TRUTH_AMP, "rotor/blades", "campbell/data/speed"):
        assert ent["/" + path]["rows"] == N_REV, path
    for path in ("families", "engine_orders", "run_range", "resonance", "labels", "axes", "ticks"):
        assert ent[f"/campbell/data/{path}"]["static"], path
    for path in ("/rotor/casing", "/rotor/probes", "/rotor/opr", "/campbell/data"):
        assert ent[path]["static"], path
    assert not any(p.startswith(("/fit", "/tw", "/resonance", "/signal")) for p in ent)  # no processing: empty views
    assert [s.application_id for s in RrdReader(out).blueprints()] == [views.APPLICATION_ID]


@pytest.mark.integration
def test_log_recording_with_processing_messages(processed_mcap, tmp_path):
    out = tmp_path / "processed.rrd"
    session = views.log_recording(processed_mcap, out, blades=[3, 7, 11])
    assert session.stats["fits"] == N_REV and session.stats["tw"] == N_REV * 5 and session.stats["resonance"] == 1
    rrd_verify(out)
    ent = rrd_entities(out)
    for leaf in ("amp_pkpk_mm", "phase_deg", "freq_hz", "vs_rpm/data/fit", "vs_rpm/data/d_eqv"):
        assert ent[f"/fit/eo_8/{leaf}"]["rows"] == N_REV, leaf
    assert ent[f"/{paths.TW_ND}"]["rows"] == N_REV
    for probe in range(5):
        assert ent[f"/{paths.tw_path(probe)}"]["static"]
    for path in (paths.RESONANCE_TABLE, f"{paths.RESONANCE_BARS}/btt", f"{paths.RESONANCE_BARS}/d_eqv"):
        assert ent["/" + path]["static"], path
    msgs = decoded(read_recording(processed_mcap).messages)
    # the whole-run travelling wave: rows ND +14 (top) .. -14 (bottom), one column per
    # revolution, magnitudes in mm, as the processor sent them
    tws = [m for k, m in msgs if k == "tw" and m.body.probe == 0]
    tensor = static_tensor(out, f"/{paths.tw_path(0)}")
    assert tensor.shape == (29, N_REV)
    np.testing.assert_allclose(tensor, np.stack([m.body.signed_spectrum() for m in tws], axis=1) * 1e3, rtol=1e-6)
    # the same matrix drawn for reading: coloured by the colour bar's map, ND ticks on the
    # left (+14 top .. -14 bottom), a colour bar ticked in mm up to the largest magnitude
    rgb = np.asarray(static_value(out, f"/{paths.tw_map_path(0)}/image", ":buffer")[0], np.uint8)
    top = max(float(static_tensor(out, f"/{paths.tw_path(j)}").max()) for j in range(5))
    np.testing.assert_array_equal(rgb.reshape(29, N_REV, 3), turbo((np.clip(tensor, 0, None) / top) ** GAMMA))
    ticks = static_value(out, f"/{paths.tw_map_path(0)}/data/ticks", ":labels")
    assert {"+14", "+10", "0", "-10", "-14"} <= set(ticks)
    bar = static_value(out, f"/{paths.tw_map_path(0)}/data/colour_ticks", ":labels")
    assert bar[0] == "0 mm" and all(t.endswith(" mm") for t in bar) and 0 < float(bar[-1][:-3]) <= top
    ys = np.asarray(static_value(out, f"/{paths.tw_map_path(0)}/data", ":translation")[0])
    assert ys.size == 3  # the plot's transform
    revs, nd = temporal(out, f"/{paths.TW_ND}", ":scalars")
    np.testing.assert_array_equal(np.ravel(nd), [m.body.nd for m in tws])
    # per EO, one amplitude series per blade, in mm, at the fit's revolution
    fits = [m for k, m in msgs if k == "fit"]
    revs, amp = temporal(out, "/fit/eo_8/amp_pkpk_mm", ":scalars")
    np.testing.assert_array_equal(revs, [m.header.revolution for m in fits])
    np.testing.assert_allclose(amp, [m.body.amp_pkpk_m * 1e3 for m in fits], rtol=1e-6)
    # amplitude against speed: (rpm, mm) points, all inside the plot box
    _, pts = temporal(out, "/fit/eo_8/vs_rpm/data/fit", ":positions")
    pts = np.asarray(pts, float)  # (n_rev, n_blades, 2)
    np.testing.assert_allclose(pts[:, 0, 0], [m.body.omega_rad_s * 30 / np.pi for m in fits], rtol=1e-6)
    box = to_box(out, "/fit/eo_8/vs_rpm/data", pts.reshape(-1, 2))
    assert box[:, 0].min() >= 0 and box[:, 0].max() <= 1 and box[:, 1].min() >= -1 / 1.6 and box[:, 1].max() <= 0
    table = static_value(out, f"/{paths.RESONANCE_TABLE}", ":text")[0]
    assert "| 28 |" in table and max(len(line) for line in table.splitlines() if line.startswith("|")) <= 40


@pytest.mark.integration
@pytest.mark.unit
def test_campbell_legend_says_which_nd_the_force_excites(short_run):
    """EO 8 aliases to ND 8 (2606 rpm), but the scenario's travelling wave is ND 1: the legend
    and the crossing (family 1 at ND 1, about 2579 rpm, where the run resonates) say ND 1."""
    info = _run_info(short_run)
    lay = CampbellLayout(info)
    frame = PlotFrame(None, paths.CAMPBELL, (0.0, lay.x_top_rpm), (0.0, lay.f_top_hz), x_label=lambda x: f"{x:g} rpm",
                      y_label=lambda f: f"{f:g} Hz")
    lay.place(frame)
    texts = [t for t, _, _ in lay.labels]
    assert "force: EO 8 x ND 1" in texts, texts
    (speed, f, text), = [c for c in lay.crossings if abs(c[0] - 2580.0) < 5.0]
    assert text.startswith("EO 8 x ND 1:")
    np.testing.assert_allclose(f, info.family_freq_hz[0, 1], rtol=1e-9)
    two = CampbellLayout(_run_info(short_run, engine_orders=(8, 16), nodal_diameters=(1, 28)))
    assert two.legend == "force: EO 8 x ND 1, EO 16 x ND -1"


def test_campbell_is_drawn_from_the_run_metadata_alone(short_mcap, tmp_path, monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("the views rebuilt the model or parsed the scenario")

    for target in ("bttsim_stream.model.build_model", "bttsim_stream.model.load_model",
                   "bttsim_stream.sim.core.load_scenario_model", "bttsim_stream.scenario.scenario_from_dict",
                   "bttsim_stream.scenario.load_scenario"):
        monkeypatch.setattr(target, refuse)
    out = tmp_path / "campbell.rrd"
    views.log_recording(short_mcap, out)
    meta = codec.decode_message(*next((m.key, m.payload) for m in read_recording(short_mcap).messages
                                      if keys.parse_key(m.key).kind == "meta")).body
    strips = np.asarray(static_value(out, "/campbell/data/families", ":strips"), float)  # (n, 2, 2)
    f_top = CampbellLayout(meta).f_top_hz
    expected = np.sort([f for f in meta.family_freq_hz.ravel() if 0 < f < f_top])
    np.testing.assert_allclose(np.sort(strips[:, 0, 1]), expected, rtol=1e-6)
    crossing = np.asarray(static_value(out, "/campbell/data/resonance", ":positions"), float)
    np.testing.assert_allclose(crossing[:, 0], 60 * crossing[:, 1] / 8)  # on the EO 8 line
    np.testing.assert_allclose(crossing[:, 1], meta.family_freq_hz[0, 1], rtol=1e-6)  # family 1, ND 1
    box = np.asarray(static_value(out, "/campbell/data/run_range", ":half_sizes"), float)
    np.testing.assert_allclose(2 * box[0, 0], np.diff(meta.speed_range_rpm), rtol=1e-6)


RPM = 2 * np.pi / 60
#: A short run through EO 8's crossing with family 1 at ND 1 (2579 rpm at zero speed, about
#: 2643 rpm with centrifugal stiffening), with the centrifugal model.
SHORT_CENTRIFUGAL = ("[speed]\nstart_rpm = 2550.0\nend_rpm = 2700.0\nduration_s = 2.0\n"
                     "[model]\ncentrifugal = true\n")


@pytest.fixture(scope="module")
def centrifugal_run(tmp_path_factory):
    """``(model, decoded run metadata, recording)`` of :data:`SHORT_CENTRIFUGAL`."""
    path = tmp_path_factory.mktemp("centrifugal") / "short.toml"
    path.write_text(SHORT_CENTRIFUGAL)
    stream = AcquisitionStream(load_scenario(path))
    out = path.with_suffix(".mcap")
    with McapRecorder(out, run_metadata=stream.run_metadata_record) as rec:
        rec.write_all([stream.meta] + [m for _, msgs in stream.batches() for m in msgs])
    return stream.sim.model, codec.decode_run_metadata(stream.meta.payload, stream.meta.key).body, out


@pytest.mark.unit
def test_centrifugal_run_metadata_carries_the_family_curves(centrifugal_run):
    model, info, mcap = centrifugal_run
    e = model.extra
    np.testing.assert_array_equal(info.family_speed_rad_s, e["speed_rad_s"])
    np.testing.assert_array_equal(info.family_freq_hz_at_speed, e["campbell_freq_hz_at_speed"])
    np.testing.assert_array_equal(info.family_freq_hz_at_speed[0], info.family_freq_hz)
    assert info.family_freq_hz_at_speed.shape == (17, 5, 15)
    # and the recording carries them
    meta = next(m for m in read_recording(mcap).messages if keys.parse_key(m.key).kind == "meta")
    back = codec.decode_run_metadata(meta.payload, meta.key).body
    np.testing.assert_array_equal(back.family_speed_rad_s, info.family_speed_rad_s)
    np.testing.assert_array_equal(back.family_freq_hz_at_speed, info.family_freq_hz_at_speed)


@pytest.mark.unit
def test_campbell_crossing_moves_onto_the_family_curve(centrifugal_run):
    from bttsim_stream.model.speed_modes import crossing_speeds, interpolate_freq_hz

    model, info, _ = centrifugal_run
    flat = CampbellLayout(dataclasses.replace(info, family_speed_rad_s=None, family_freq_hz_at_speed=None))
    curved = CampbellLayout(info)
    assert flat.curve_hz is None and [c[2] for c in flat.crossings] == ["EO 8 x ND 1: 2579 rpm"]
    assert [c[2] for c in curved.crossings] == ["EO 8 x ND 1: 2643 rpm"]
    # where the model itself puts it (crossing_speeds: a 2001-point grid, then linear)
    (speed, f, _), = curved.crossings
    lo, hi = info.speed_range_rpm
    want = crossing_speeds(model, [8], lo * RPM, hi * RPM) / RPM
    assert abs(speed - want[0]) < 0.01, (speed, want)
    # and on the EO 8 line and the family 1, ND 1 curve (the simulator's interpolation)
    f_curve = interpolate_freq_hz(info.family_speed_rad_s, info.family_freq_hz_at_speed[:, 0, 1], speed * RPM)
    np.testing.assert_allclose([f, f_curve], 8 * speed / 60, rtol=1e-10)
    np.testing.assert_allclose(flat.crossings[0][0], 60 * info.family_freq_hz[0, 1] / 8)
    # each (family, ND) is one curve inside the plot, rising with speed from its zero-speed value
    for i, lines in curved.family_lines():
        for line in lines:
            x, y = line.T
            assert x[0] == 0 and np.all(np.diff(x) > 0) and x[-1] == curved.x_top_rpm
            table = interpolate_freq_hz(info.family_speed_rad_s, info.family_freq_hz_at_speed[:, i], x * RPM)
            assert np.abs(table - y[:, None]).max(axis=0).min() < 1e-9  # one ND's curve, Hz
    fam1 = curved.family_lines()[0][1]
    assert len(fam1) == 15 and all(np.all(np.diff(line[:, 1]) > 0) for line in fam1)


@pytest.mark.unit
def test_campbell_curves_are_cut_at_the_top_and_labels_do_not_overlap(centrifugal_run):
    _, info, _ = centrifugal_run
    for changes in ({}, {"engine_orders": (8, 3), "nodal_diameters": (1, 3)}, {"speed_range_rpm": (1000.0, 4000.0)}):
        lay = CampbellLayout(dataclasses.replace(info, **changes))
        for _, lines in lay.family_lines():
            for line in lines:
                assert np.all((line[:, 1] >= 0) & (line[:, 1] <= lay.f_top_hz * (1 + 1e-12)))
        frame = PlotFrame(None, paths.CAMPBELL, (0.0, lay.x_top_rpm), (0.0, lay.f_top_hz),
                          x_label=lambda x: f"{x:g} rpm", y_label=lambda f: f"{f:g} Hz")
        lay.place(frame)
        boxes = [label_box(text, *spot) for text, spot, _ in lay.labels]
        for a, b in combinations(boxes + frame.obstacles(), 2):
            assert not (a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]), (a, b)


@pytest.mark.integration
def test_campbell_of_a_centrifugal_recording_draws_curves(centrifugal_run, tmp_path, monkeypatch):
    _, info, mcap = centrifugal_run
    for target in ("bttsim_stream.model.build_model", "bttsim_stream.model.load_model",
                   "bttsim_stream.sim.core.load_scenario_model", "bttsim_stream.scenario.load_scenario"):
        monkeypatch.setattr(target, lambda *a, **k: (_ for _ in ()).throw(AssertionError("model rebuilt")))
    out = tmp_path / "centrifugal.rrd"
    views.log_recording(mcap, out)
    lay = CampbellLayout(info)
    crossing = np.asarray(static_value(out, "/campbell/data/resonance", ":positions"), float)
    np.testing.assert_allclose(crossing, [[lay.crossings[0][0], lay.crossings[0][1]]], rtol=1e-6)
    strips = static_value(out, "/campbell/data/families", ":strips")
    lines = [line for _, ls in lay.family_lines() for line in ls]
    assert len(strips) == len(lines) and min(len(s) for s in strips) > 100
    for got, want in zip(strips, lines):
        np.testing.assert_allclose(np.asarray(got, float), want, rtol=1e-6)


@pytest.mark.integration
def test_log_recording_without_sensing_angles_or_families(short_mcap, tmp_path):
    """An older recording's metadata: Eq. 1 calibrated, Campbell without families."""
    src = tmp_path / "old-meta.mcap"
    rewrite_metadata(short_mcap, src, sensing_angles_rad=None, family_freq_hz=None, speed_range_rpm=(0.0, 0.0))
    out = tmp_path / "old-meta.rrd"
    views.log_recording(src, out)
    rrd_verify(out)
    ent = rrd_entities(out)
    assert "/campbell/data/families" not in ent and ent["/campbell/data/engine_orders"]["static"]
    assert ent["/campbell/data/speed"]["rows"] == N_REV  # drawn up to the speeds seen
    revs, d_mm = temporal(out, f"/{paths.displacement_path(2)}/btt", ":scalars")  # blades 0 and 14
    truth = truth_of(decoded(read_recording(short_mcap).messages))
    d_eq1 = np.stack([truth[k].d_eq1_m[0, [0, 14], 2] for k in revs])
    reference = np.median(d_eq1[:CALIBRATION_REVOLUTIONS], axis=0)
    np.testing.assert_allclose(np.asarray(d_mm)[:-1] * 1e-3, (d_eq1 - reference)[:-1], rtol=0, atol=1e-8)


@pytest.mark.integration
def test_log_recording_bad_input_is_a_one_line_error(tmp_path):
    with pytest.raises(BttsimError):
        views.log_recording(tmp_path / "missing.mcap", tmp_path / "x.rrd")
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not an mcap file at all")
    with pytest.raises(BttsimError):
        views.log_recording(bad, tmp_path / "x.rrd")


@pytest.mark.integration
def test_live_views_fed_message_by_message(processed_mcap, tmp_path):
    out = tmp_path / "live.rrd"
    rec, _ = views.open_recording(rrd_path=out)
    live = views.LiveViews(rec, live=True, flush_period_s=0.01, tw_window=32, tw_period_s=0.0)
    msgs = read_recording(processed_mcap).messages
    for m in msgs:
        live.feed(m.key, m.payload)
    live.feed("bttsim/rig1/alive/sim", b"")           # not a message: ignored
    live.feed("bttsim/rig1/opr", b"\xff\xff garbage")  # counted, skipped
    report = next(m for m in msgs if m.key.endswith("/resonance"))  # another run's report: not shown
    d = codec.decode_message(report.key, report.payload)
    live.feed(report.key, codec.encode_resonance_report(codec.Header("forged", 99, -1, 0.0), d.body))
    live.close()
    rec.disconnect()
    assert live.stats["revolutions"] == N_REV and live.stats["bad"] == 1 and live.stats["ignored"] == 2
    assert live.stats["fits"] == N_REV and live.stats["resonance"] == 1
    rrd_verify(out)
    ent = rrd_entities(out)
    assert ent[f"/{paths.SPEED}"]["rows"] == N_REV and ent[f"/{paths.displacement_path(4)}/btt"]["rows"] == N_REV
    assert ent["/fit/eo_8/amp_pkpk_mm"]["rows"] == N_REV and ent[f"/{paths.TW_ND}"]["rows"] == N_REV
    assert ent[f"/{paths.tw_path(0)}"]["rows"] > 1 and not ent[f"/{paths.tw_path(0)}"]["static"]  # rolling window
    assert ent[f"/{paths.RESONANCE_TABLE}"]["rows"] == 1


def _held_bytes(obj, seen: set) -> int:
    """Bytes the views hold in ``obj``: arrays, byte strings and containers, followed through
    this package's objects (not Rerun's: its stream is measured by ``bench_memory.py``)."""
    if id(obj) in seen or obj is None or isinstance(obj, (bool, int, float, str, type)):
        return 0
    seen.add(id(obj))
    if isinstance(obj, np.ndarray):
        return obj.nbytes
    if isinstance(obj, (bytes, bytearray)):
        return len(obj)
    if isinstance(obj, dict):
        return 8 * len(obj) + sum(_held_bytes(k, seen) + _held_bytes(v, seen) for k, v in obj.items())
    if isinstance(obj, (list, tuple, set, frozenset, deque)):
        return 8 * len(obj) + sum(_held_bytes(v, seen) for v in obj)
    if not type(obj).__module__.startswith("bttsim_stream"):
        return 0
    names = list(getattr(obj, "__dict__", {})) + [n for c in type(obj).__mro__ for n in getattr(c, "__slots__", ())]
    return sum(_held_bytes(getattr(obj, n, None), seen) for n in names if n != "rec")


@pytest.mark.integration
def test_live_views_hold_the_same_whatever_the_runs_length(processed_mcap, tmp_path, monkeypatch):
    """The live views' state is bounded: N and 4N revolutions of fits, travelling waves and
    truth (the short run's, repeated at later revolutions) leave the same held bytes."""
    monkeypatch.setattr("bttsim_stream.views.fits.TRUTH_HISTORY", 256)  # the bound, reached quickly
    msgs = read_recording(processed_mcap).messages
    meta = msgs[0]
    kept = [(keys.parse_key(m.key), codec.decode_message(m.key, m.payload)) for m in msgs[1:]]
    kept = [(info, d) for info, d in kept if info.kind in ("truth", "fit", "tw")]

    def held(copies: int) -> int:
        rec, _ = views.open_recording(rrd_path=tmp_path / f"held{copies}.rrd")
        live = views.LiveViews(rec, live=True, flush_period_s=1e9, tw_window=64, tw_period_s=0.0)
        live.feed(meta.key, meta.payload)
        for c in range(copies):
            for info, d in kept:
                h = d.header
                header = dataclasses.replace(h, revolution=h.revolution + c * N_REV, t_s=h.t_s + c * 3.0)
                live.feed_decoded(views.live.Incoming(info.kind, info.rig, dataclasses.replace(d, header=header)))
            live.flush()
        size = _held_bytes(live, set())
        live.close()
        rec.disconnect()
        assert live.stats["fits"] == copies * N_REV and live.stats["tw"] == copies * N_REV * 5
        return size

    short, long = held(4), held(16)
    assert long <= 1.05 * short, (short, long)


def test_viewer_node_keeps_few_samples_waiting_in_zenoh(tmp_path, monkeypatch):
    """The viewer's live FIFO is small: a sample waiting there holds Zenoh's memory."""
    from bttsim_stream.nodes import viewer_node
    from bttsim_stream.runtime import SINK_FIFO_SIZE

    asked = {}

    def node_session(*args, **kwargs):
        asked.update(kwargs)
        raise RuntimeError("stop here")

    monkeypatch.setattr(viewer_node, "node_session", node_session)
    parser = argparse.ArgumentParser()
    viewer_node.add_arguments(parser)
    args = parser.parse_args(["--rrd", str(tmp_path / "v.rrd")])
    with pytest.raises(RuntimeError, match="stop here"):
        viewer_node.main(None, args)
    assert asked["fifo_size"] == SINK_FIFO_SIZE <= 256


@pytest.mark.integration
def test_live_views_add_the_views_of_an_engine_order_the_metadata_lacks(short_run, tmp_path, caplog):
    stream, messages = short_run
    seq = Sequencer()
    key = keys.fits_key(stream.rig)
    nb = stream.info.n_blades
    fits = []
    for rev in range(3):
        fit = RevolutionFit(engine_order=9, omega_rad_s=262.0, freq_hz=9 * 262.0 / (2 * np.pi), cn=1.5,
                            amp_pkpk_m=np.full(nb, 1e-4), phase_rad=np.zeros(nb), dc_m=np.zeros(nb),
                            residual_rms_m=np.zeros(nb), amp_std_m=np.zeros(nb))
        fits.append(codec.encode_fit(codec.Header(stream.run_id, seq.next(key), rev, 0.02 * rev), fit))
    rec, _ = views.open_recording(rrd_path=tmp_path / "eo9.rrd")
    live = views.LiveViews(rec, live=True)
    live.feed(stream.meta.key, stream.meta.payload)
    with caplog.at_level("INFO", logger="bttsim.views"):
        for payload in fits:
            live.feed(key, payload)
        live.close()
    rec.disconnect()
    assert live.stats["fits"] == 3 and "layout updated" in caplog.text
    ent = rrd_entities(tmp_path / "eo9.rrd")
    assert ent["/fit/eo_9/amp_pkpk_mm"]["rows"] == 3 and ent["/fit/eo_9/vs_rpm/data/fit"]["rows"] == 3


# --------------------------------------------------------------------------------------
# The viewer node (real processes on loopback)
# --------------------------------------------------------------------------------------


def _wait_for_rows(path: Path, entity: str, n: int, procs, timeout_s: float = 180.0) -> int:
    """Poll the .rrd being written until ``entity`` has ``n`` rows (the viewer is showing the
    run); fails if a process ends first or time runs out."""
    deadline = time.monotonic() + timeout_s
    rows = 0
    while time.monotonic() < deadline:
        assert all(p.poll() is None for p in procs), "a node ended before the viewer showed the run"
        if path.exists():
            try:
                rows = rrd_entities(path).get(entity, {}).get("rows", 0)
            except Exception:  # noqa: BLE001 -- a chunk still being written
                rows = 0
            if rows >= n:
                return rows
        time.sleep(0.2)
    raise AssertionError(f"{entity}: {rows} rows after {timeout_s} s")


@pytest.mark.integration
@pytest.mark.parametrize("stop_by", ["sim-ends", "sigterm"])
def test_viewer_node_follows_a_live_simulator_and_leaves_a_valid_rrd(short_scenario, tmp_path, stop_by):
    port = free_port()
    out = tmp_path / "live.rrd"
    viewer = _start("bttsim_stream.nodes.viewer_node", "-e", f"tcp/127.0.0.1:{port}", "--rig", "rig1",
                    "--rrd", out)
    rate = "10" if stop_by == "sim-ends" else "0.05"  # 0.05: a 60 s run, stopped once it shows
    sim = _start("bttsim_stream.nodes.sim_node", short_scenario, "-l", f"tcp/127.0.0.1:{port}", "--rate", rate,
                 "--wait-for", "1", "--wait-timeout", "120")
    try:
        if stop_by == "sim-ends":
            assert sim.wait(timeout=180) == 0, sim.stderr.read()
            text, err = viewer.communicate(timeout=120)  # the viewer stops when the simulator is gone
        else:
            _wait_for_rows(out, f"/{paths.SPEED}", 3, (viewer, sim))
            viewer.send_signal(signal.SIGTERM)
            text, err = viewer.communicate(timeout=120)
        # stopped mid-run, the views miss the rest of the run: exit 3, the missing counted per key
        assert viewer.returncode == (0 if stop_by == "sim-ends" else 3), err
    finally:
        _stop(sim), _stop(viewer)
    counts = json.loads(text.strip().splitlines()[-1])
    rrd_verify(out)
    ent = rrd_entities(out)
    rows = ent[f"/{paths.SPEED}"]["rows"]
    if stop_by == "sim-ends":
        assert counts["complete"] and counts["missing"] == 0 and counts["rejected"] == 0, counts
        assert rows == N_REV
        assert ent[f"/{paths.displacement_path(0)}/btt"]["rows"] == N_REV
        assert ent[f"/{paths.TRUTH_AMP}"]["rows"] == N_REV
    else:
        assert 3 <= rows < N_REV
        missing = counts["missing_by_key"]
        assert not counts["complete"] and "INCOMPLETE" in err, err
        # the OPR pulses not received are its tail, and the revolutions shown were received
        assert missing["bttsim/rig1/opr"]["head"] == missing["bttsim/rig1/opr"]["gaps"] == 0, missing
        assert rows <= N_REV - missing["bttsim/rig1/opr"]["tail"] < N_REV, (rows, missing)
        assert counts["missing"] == sum(sum(m.values()) for m in missing.values())
    assert ent["/campbell/data/families"]["static"] and ent["/rotor/blades"]["rows"] == rows


@pytest.mark.integration
def test_viewer_node_without_an_output_is_a_one_line_error():
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.nodes.viewer_node", "--rig", "rig1"],
                         cwd=REPO, capture_output=True, text=True, timeout=60)
    assert res.returncode == 2
    assert res.stderr.strip().startswith("bttsim: error:") and len(res.stderr.strip().splitlines()) == 1


@pytest.mark.integration
def test_bttsim_view_of_the_sample_recording(tmp_path):
    """`bttsim view recordings/<sample>.mcap --rrd out.rrd`: processed first, every view present."""
    out = tmp_path / "sample.rrd"
    res = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", "view",
                          str(REPO / "recordings" / "resonance_window.mcap"), "--rrd", str(out)],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    rrd_verify(out)
    ent = rrd_entities(out)
    for path in (paths.tw_path(0), "fit/eo_8/amp_pkpk_mm", "fit/eo_8/vs_rpm/data/fit", paths.TRUTH_AMP,
                 f"{paths.displacement_path(0)}/btt", "rotor/blades", "campbell/data/engine_orders",
                 paths.RESONANCE_TABLE):
        assert "/" + path in ent, path


# --------------------------------------------------------------------------------------
# The web viewer in headless Chromium (slow: software rendering)
# --------------------------------------------------------------------------------------

_SERVE = textwrap.dedent("""
    import sys, time
    from bttsim_stream import views
    s = views.log_recording(sys.argv[1], None, serve_web=True, web_port=int(sys.argv[2]),
                            grpc_port=int(sys.argv[3]))
    print(s.sinks.web_url, flush=True)
    time.sleep(float(sys.argv[4]))
""")

_CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def _loopback_only(route):
    from urllib.parse import urlparse

    host = urlparse(route.request.url).hostname
    if host in ("127.0.0.1", "localhost") or route.request.url.startswith(("data:", "blob:")):
        return route.continue_()
    return route.abort()


def _capture(url: str | None, path: Path, user_data: Path, *, budget_s: float, first_wait_s: float = 45.0,
             every_s: float = 15.0, done=lambda pixels: True) -> np.ndarray:
    """Open ``url`` (or a blank page) in headless Chromium and screenshot it to ``path`` every
    ``every_s`` after ``first_wait_s`` until ``done(pixels)`` or ``budget_s`` is spent; returns
    the last screenshot's RGB pixels. Only loopback requests are let through."""
    from playwright.sync_api import sync_playwright

    deadline = time.monotonic() + budget_s
    with sync_playwright() as p:
        ctx = p.chromium.launch_persistent_context(str(user_data), executable_path=CHROMIUM,
                                                   args=_CHROMIUM_ARGS, headless=True,
                                                   viewport={"width": 1600, "height": 1000})
        try:
            page = ctx.new_page()
            page.route("**/*", _loopback_only)
            if url:
                page.goto(url, wait_until="domcontentloaded", timeout=120_000)
            page.wait_for_timeout(first_wait_s * 1000)
            while True:
                page.screenshot(path=str(path), timeout=180_000)
                pixels = _png_rgb(path)
                if done(pixels) or time.monotonic() > deadline:
                    return pixels
                page.wait_for_timeout(every_s * 1000)
        finally:
            ctx.close()


def _png_rgb(path: Path) -> np.ndarray:
    import matplotlib.image as mpimg

    img = mpimg.imread(str(path))
    if img.dtype != np.uint8:
        img = np.round(img * 255).astype(np.uint8)
    return img[..., :3]


def _n_colours(pixels: np.ndarray) -> int:
    flat = pixels.reshape(-1, 3).astype(np.int64)
    return np.unique((flat[:, 0] << 16) | (flat[:, 1] << 8) | flat[:, 2]).size


def _plot_checks(pixels: np.ndarray) -> dict[str, bool]:
    """What the overview tab must show once drawn (1600 x 1000 page, 3 x 2 grid of views)."""
    h, w = pixels.shape[:2]
    background = np.median(pixels.reshape(-1, 3), axis=0)
    busy = np.abs(pixels.astype(int) - background).sum(axis=2) > 60
    cells = [busy[r * h // 2:(r + 1) * h // 2, c * w // 3:(c + 1) * w // 3].mean()
             for r in range(2) for c in range(3)]
    top_left, top_right = pixels[90:h // 2, :w // 3], pixels[90:h // 2, 2 * w // 3:]
    return {
        # many colours (heat map, blade colours, lines), spread over the page
        "many colours": _n_colours(pixels) > 800,
        "5 of 6 views drawn": sum(c > 0.01 for c in cells) >= 5,
        # ours specifically: the travelling-wave heat map (a colour gradient, top left) and
        # blade 0 in orange in the rotor view (top right)
        "heat map": _n_colours(top_left) > 100,
        "rotor": int((np.abs(top_right.astype(int) - [230, 120, 20]).sum(axis=2) < 60).sum()) > 50,
    }


@pytest.mark.browser
def test_web_viewer_draws_the_plots(processed_mcap, tmp_path):
    if CHROMIUM is None:
        pytest.skip("Chromium not installed (apt-get install chromium)")
    pytest.importorskip("playwright", reason="Playwright not installed (pip install playwright)")
    web_port, grpc_port = free_port(), free_port()
    log_path = tmp_path / "server.log"
    with open(log_path, "w") as log_file:  # a file, not a pipe: the server logs for minutes
        server = subprocess.Popen([sys.executable, "-c", _SERVE, str(processed_mcap), str(web_port),
                                   str(grpc_port), "600"], cwd=REPO, stdout=subprocess.PIPE, stderr=log_file,
                                  text=True)
    try:
        url = server.stdout.readline().strip()
        assert url.startswith(f"http://127.0.0.1:{web_port}/"), log_path.read_text()[-2000:]
        from _net import is_loopback, listening_of

        served = listening_of([server.pid])  # our page server and Rerun's data server: loopback only
        assert ("127.0.0.1", web_port) in served and all(is_loopback(addr) for addr, _ in served), served
        blank = _capture(None, tmp_path / "blank.png", tmp_path / "profile-blank", budget_s=0, first_wait_s=1)
        shot = tmp_path / "views.png"
        pixels = _capture(url, shot, tmp_path / "profile", budget_s=420,
                          done=lambda px: all(_plot_checks(px).values()))
    finally:
        _stop(server)
    assert not any(_plot_checks(blank).values())
    checks = _plot_checks(pixels)
    assert all(checks.values()), f"{checks}: see {shot}"
    target = os.environ.get("BTTSIM_SAVE_SCREENSHOT")
    if target:
        shutil.copyfile(shot, target)


# --------------------------------------------------------------------------------------
# The raw signal view
# --------------------------------------------------------------------------------------


def test_raw_signal_view_shows_the_selected_blades_window_level_and_toa(tmp_path):
    """A run with raw signals on the bus: per revolution, probe 0's window of blade 0 (the
    first selected blade) as logged is the decoded window, the trigger levels sit at the arming
    level and at the window's own constant-fraction level (baseline of its first 4 samples +
    f (max - baseline)), and the TOA line stands at the TOA published on toa/0 -- or is empty,
    with a "missing pulse" label, where that TOA is NaN. A recording without raw signals logs
    no signal entity (test_log_recording_of_a_raw_acquisition)."""
    scn_text = SHORT + ("[acquisition]\nclock_hz = 1e8\n[acquisition.signal]\nenabled = true\npublish = true\n"
                        'probe_type = "capacitive"\ntrigger = "constant_fraction"\nfraction = 0.4\n'
                        "clearance_m = 1e-3\nnoise_v = 0.01\nlevel_v = 0.318\n")
    path = tmp_path / "signal.toml"
    path.write_text(scn_text)
    stream = AcquisitionStream(load_scenario(path))
    messages = [stream.meta] + [m for _, msgs in stream.batches() for m in msgs]
    mcap = tmp_path / "signal.mcap"
    with McapRecorder(mcap, run_metadata=stream.run_metadata_record) as rec:
        rec.write_all(messages)
    out = tmp_path / "signal.rrd"
    session = views.log_recording(mcap, out)
    assert session.stats["signal"] == N_REV and session.stats["bad"] == 0
    rrd_verify(out)
    data = f"/{paths.signal_path(0)}/data"
    ent = rrd_entities(out)
    for leaf in ("window", "samples", "level", "toa", "note"):
        assert ent[f"{data}/{leaf}"]["rows"] == N_REV, leaf
    assert ent[data]["static"] and ent[f"{data}/axes"]["static"]
    assert not any(p.startswith(f"/{paths.signal_path(1)}") for p in ent)  # one probe shown
    toa0 = {codec.decode_message(m.key, m.payload).header.revolution: codec.decode_message(m.key, m.payload).body
            for m in messages if m.key == keys.toa_key("rig1", 0)}
    sig0 = {codec.decode_message(m.key, m.payload).header.revolution: codec.decode_message(m.key, m.payload).body
            for m in messages if m.key == keys.signal_key("rig1", 0)}
    revs, windows = temporal(out, f"{data}/window", ":strips")
    _, levels = temporal(out, f"{data}/level", ":strips")
    _, toas = temporal(out, f"{data}/toa", ":strips")
    _, notes = temporal(out, f"{data}/note", ":labels")
    assert list(revs) == list(range(N_REV))
    n_missing = 0
    for r, win, lev, toa, note in zip(revs, windows, levels, toas, notes):
        t, v = sig0[r].window(0)
        xy = np.asarray(win[0])
        np.testing.assert_allclose(xy[:, 0], (t - t[0]) * 1e6, atol=1e-4)
        np.testing.assert_allclose(xy[:, 1], v, atol=1e-6)
        base = v[:4].mean()
        np.testing.assert_allclose([np.asarray(s)[0, 1] for s in lev], [0.318, base + 0.4 * (v.max() - base)],
                                   atol=1e-6)
        published = toa0[r].toa_s[0]
        if np.isnan(published):
            n_missing += 1
            assert not toa
            assert "missing pulse" in note[0]
        else:
            x = np.asarray(toa[0])[:, 0]
            np.testing.assert_allclose(x, (published - t[0]) * 1e6, atol=1e-4)
    assert n_missing > 0  # the case that matters is exercised


def test_live_views_add_the_raw_signal_tab_when_signals_arrive(tmp_path, caplog):
    path = tmp_path / "signal.toml"
    path.write_text(SHORT + "[acquisition.signal]\nenabled = true\npublish = true\n")
    stream = AcquisitionStream(load_scenario(path), n_revolutions=12)
    messages = [stream.meta] + [m for _, msgs in stream.batches() for m in msgs]
    rec, _ = views.open_recording(rrd_path=tmp_path / "live.rrd")
    live = views.LiveViews(rec, live=True, flush_period_s=0.0, signal_probe=2, blades=[5])
    with caplog.at_level("INFO", logger="bttsim.views"):
        for m in messages:
            live.feed(m.key, m.payload)
        live.close()
    rec.disconnect()
    assert "raw signals on the bus: layout updated" in caplog.text and live.stats["signal"] == 12
    ent = rrd_entities(tmp_path / "live.rrd")
    assert ent[f"/{paths.signal_path(2)}/data/window"]["rows"] == 12
    _, notes = temporal(tmp_path / "live.rrd", f"/{paths.signal_path(2)}/data/note", ":labels")
    assert all("blade 5" in n[0] for n in notes)
