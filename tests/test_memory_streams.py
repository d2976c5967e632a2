"""Bounded-memory paths give the outputs of the whole-run ones: the export's row blocks and
streamed truth, the views' batched logging of a recording, the dense travelling-wave store."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from bttsim_stream import export
from bttsim_stream.bus.recording import McapRecorder, RecordingScan, read_recording
from bttsim_stream.cli import main
from bttsim_stream.offline import load_run, with_processing
from bttsim_stream.process import scratch_result
from bttsim_stream.views import travelling_wave as tw

SCENARIO = """
[speed]
start_rpm = 2450.0
end_rpm = 2700.0
duration_s = 3.0
"""


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    d = tmp_path_factory.mktemp("memory")
    (d / "s.toml").write_text(SCENARIO)
    assert main(["simulate", str(d / "s.toml"), "--out", str(d / "run.mcap"), "-q"]) == 0
    return d / "run.mcap"


def _files(folder: Path) -> dict:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_export_blocks_give_the_bytes_of_one_block(recording, tmp_path, monkeypatch):
    export.export_run(recording, tmp_path / "one", "csv")  # a 3 s run: one block per table
    monkeypatch.setattr(export, "BLOCK_ROWS", 700)  # many blocks, cut inside tables of every shape
    monkeypatch.setattr(export, "CSV_ROWS", 333)  # each formatted in pieces
    monkeypatch.setattr(scratch_result, "SCRATCH_BLOCK", 50)  # the fits and spectra written by short blocks
    export.export_run(recording, tmp_path / "many", "csv")
    one, many = _files(tmp_path / "one"), _files(tmp_path / "many")
    assert set(one) >= {"toa.csv", "truth.csv", "fit.csv", "tw_probe.csv"} and one == many


def test_export_truth_out_of_order_falls_back_to_the_whole_run(recording, tmp_path, monkeypatch):
    scan = RecordingScan(recording)
    msgs = list(scan)
    truth = [i for i, m in enumerate(msgs) if m.key.endswith("/truth")]
    i, j = truth[3], truth[4]
    msgs[i], msgs[j] = msgs[j], msgs[i]  # revolution 4's truth before revolution 3's
    odd = tmp_path / "odd.mcap"
    with McapRecorder(odd, run_metadata=scan.metadata["bttsim.run"]) as rec:
        rec.write_all(msgs)
    run = load_run(odd, truth_fields=())
    with pytest.raises(export.Unstreamable):
        list(export._truth_stream(odd, run.revolution, run.meta.n_blades, run.meta.n_probes, run.meta.rig))
    counts = export.export_run(odd, tmp_path / "odd", "csv")
    back = export.read_tables(tmp_path / "odd")["truth"]
    whole = export.run_tables(load_run(odd)).table("truth")  # every truth field held
    assert counts["truth"] == whole["revolution"].size
    for k, v in whole.items():
        np.testing.assert_array_equal(back[k], v)


def _rrd_data(path: Path) -> tuple[dict, dict]:
    """Temporal rows of each entity (sorted, row ids left out) and the last static value of
    every component."""
    import pyarrow as pa
    from rerun.chunk import RrdReader

    def py(col):
        if pa.types.is_duration(col.type) or pa.types.is_timestamp(col.type):
            col = col.cast(pa.int64())
        return col.to_pylist()

    temporal: dict = {}
    static: dict = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for chunk in RrdReader(path).stream():
            batch = chunk.to_record_batch()
            names = [n for n in batch.schema.names if "RowId" not in n and n != "RecordingInfo:start_time"]
            if chunk.is_static:
                for n in names:
                    static[(chunk.entity_path, n)] = py(batch.column(n))[-1]
                continue
            cols = {n: py(batch.column(n)) for n in names}
            rows = temporal.setdefault(chunk.entity_path, [])
            rows += [repr(sorted((n, cols[n][r]) for n in names)) for r in range(batch.num_rows)]
    return {k: sorted(v) for k, v in temporal.items()}, static


@pytest.mark.integration
def test_views_of_a_recording_logged_in_batches_are_the_whole_run_ones(recording, tmp_path, monkeypatch):
    from bttsim_stream.views import recording as view_recording

    src = with_processing(recording, tmp_path / "processed.mcap")
    kinds = {m.key.rsplit("/", 2)[-1] for m in read_recording(src).messages}
    assert {"fit", "resonance"} <= kinds
    monkeypatch.setattr(view_recording, "FLUSH_EVERY", 1 << 30)  # one flush, at the end
    view_recording.log_recording(src, tmp_path / "one.rrd")
    monkeypatch.setattr(view_recording, "FLUSH_EVERY", 97)
    session = view_recording.log_recording(src, tmp_path / "many.rrd")
    assert session.stats["revolutions"] > 100 and session.stats["fits"] > 100
    one, many = _rrd_data(tmp_path / "one.rrd"), _rrd_data(tmp_path / "many.rrd")
    assert len(one[0]) > 10 and len(one[1]) > 100
    assert one[0] == many[0] and one[1] == many[1]


class _Header:
    def __init__(self, revolution):
        self.revolution, self.t_s = revolution, 0.01 * revolution


class _Body:
    def __init__(self, probe, fwd, bwd):
        self.probe, self.forward_m, self.backward_m, self.nd = probe, fwd, bwd, 1


class _Msg:
    def __init__(self, rev, probe, fwd, bwd):
        self.header, self.body = _Header(rev), _Body(probe, fwd, bwd)


@pytest.mark.parametrize("live", [False, True])
def test_dense_wave_store_is_the_dict_of_spectra(live):
    """Messages out of order and repeated, two probes: the matrix logged is the one a dict
    revolution -> spectrum (the later message wins) gives."""
    rng = np.random.default_rng(3)
    n_nd, window = 4, 16
    msgs = []
    for rev in list(range(40)) + [7, 39, 12] + list(range(45, 90, 3)) + [60]:
        for probe in (0, 1):
            msgs.append(_Msg(rev, probe, rng.random(n_nd) * 1e-4, rng.random(n_nd) * 1e-4))
    rng.shuffle(msgs[:30])
    logged = []

    class Out:
        def __init__(self):
            self.live = live

        def style(self, *a):
            pass

        def scalars(self, *a):
            pass

    view = tw.TravellingWaveView(Out(), window=window, period_s=0.0)
    view._log_matrices = lambda: logged.append({p: (s.hi, s.matrix(s.hi - window + 1 if live else s.lo, s.hi))
                                                for p, s in view._spectra.items()})
    for k in range(0, len(msgs), 11):  # flushed in batches
        for m in msgs[k:k + 11]:
            view.add(m)
        view.flush(final=k + 11 >= len(msgs))
    spectra: dict = {}
    for m in msgs:
        f, b = m.body.forward_m, m.body.backward_m
        spec = np.concatenate([f[:0:-1], np.fmax(f[:1], b[:1]), b[1:]]) * 1e3
        spectra.setdefault(m.body.probe, {})[m.header.revolution] = spec.astype(np.float32)
    for probe, by_rev in spectra.items():
        last = max(by_rev)
        first = last - window + 1 if live else min(by_rev)
        want = np.zeros((2 * n_nd - 1, last - first + 1), np.float32)
        for r, spec in by_rev.items():
            if r >= first:
                want[:, r - first] = spec
        hi, got = logged[-1][probe]
        assert hi == last
        np.testing.assert_array_equal(got, want)
    if live:  # the window only is kept
        assert all(s._seen.size <= 2 * window + 64 for s in view._spectra.values())


def test_whole_recording_travelling_waves_are_not_held_in_memory():
    """A whole recording's spectra wait for the final draw in scratch files: 16 times the
    revolutions leave the view's memory as it was."""
    import tracemalloc

    class Out:
        live = False

        def style(self, *a):
            pass

        def scalars(self, *a):
            pass

    def held(n_rev: int) -> int:
        rng = np.random.default_rng(1)
        view = tw.TravellingWaveView(Out())
        tracemalloc.start()
        base = tracemalloc.get_traced_memory()[0]
        for lo in range(0, n_rev, 500):
            for rev in range(lo, min(lo + 500, n_rev)):
                for probe in range(3):
                    view.add(_Msg(rev, probe, rng.random(15) * 1e-4, rng.random(15) * 1e-4))
            view.flush()
        size = tracemalloc.get_traced_memory()[0] - base
        tracemalloc.stop()
        last = {p: s.matrix(s.lo, s.hi) for p, s in view._spectra.items()}
        assert all(m.shape == (29, n_rev) and m.any() for m in last.values())
        return size

    short, long = held(500), held(8000)
    assert long < short + 64_000, (short, long)  # 8000 revolutions of 3 probes would be 2.8 MB
