"""The live run's per-revolution state in bounded memory: the recent rows of the live
displacements, the TOA history spilled to a scratch file, and the streaming processor with
both giving the same outputs and final report as with everything held."""

import errno

import numpy as np
import pytest

from bttsim_stream.process import history
from bttsim_stream.process.history import RecentRows, ScratchRows, SparseRows, SpilledRows
from bttsim_stream.process.options import ProcessOptions
from bttsim_stream.process.streaming import StreamingProcessor


def test_recent_rows_keep_what_is_asked_for_in_a_bounded_buffer():
    r = RecentRows((2, 3), capacity=8)
    for k in range(10_000):
        r.drop_before(k - 5)
        row = r.next_row()
        assert np.isnan(row).all()  # a new row starts at the fill value, whatever was there
        row[...] = k
        assert r.row(k)[0, 0] == k
    assert r.n == 10_000 and r._a.shape[0] <= 16  # compacted, not grown
    np.testing.assert_array_equal(r.rows(9_995, 10_000)[:, 1, 2], np.arange(9_995, 10_000))
    with pytest.raises(IndexError):
        r.row(9_000)
    with pytest.raises(IndexError):
        r.rows(9_990, 10_001)
    grown = RecentRows(capacity=4)  # nothing dropped: it grows and keeps every row
    for k in range(100):
        grown.append(k)
    np.testing.assert_array_equal(grown.rows(0, 100), np.arange(100))
    flags = RecentRows(dtype=bool, fill=False)
    flags.append(True)
    assert flags.row(0) and flags.next_row() == np.False_


def test_spilled_rows_read_back_across_file_and_memory():
    rng = np.random.default_rng(4)
    ref = rng.normal(size=(103, 4, 2))
    ref[7, 1] = np.nan
    s = SpilledRows((4, 2), keep=5)
    for k in range(103):
        s.append(ref[k])
        s.row(k)[0, 0] += 1.0  # the newest rows change in place (rows refused after the fact)
    ref[:, 0, 0] += 1.0
    assert s.spilled == 95 and s.n == 103
    np.testing.assert_array_equal(s.array(), ref)
    for a, b in ((0, 3), (90, 100), (94, 96), (95, 103), (100, 103), (50, 50), (-3, 200)):
        np.testing.assert_array_equal(s.rows(a, b), ref[max(a, 0):min(b, 103)])
    with pytest.raises(IndexError):
        s.row(10)  # spilled: final
    s.close()
    small = SpilledRows((3,), keep=100)  # never spilled: no file at all
    small.append([1.0, 2.0, 3.0])
    assert small.spilled == 0 and small._file is None
    np.testing.assert_array_equal(small.array(), [[1.0, 2.0, 3.0]])


def _stream_all(run, proc, call_nsv: bool):
    outs = []
    for n in range(run.opr_s.size):
        outs += proc.push(n, run.opr_s[n], run.toa_s[n])
        if call_nsv:
            proc.nsv_ready()  # as the processor node does: the NSV blocks done let rows go
    return outs + proc.flush()


@pytest.mark.slow
def test_scratch_rows_read_back_what_was_written_by_rows_and_by_columns():
    rng = np.random.default_rng(4)
    a = rng.normal(size=(1000, 7, 3))
    a[rng.random(a.shape) < 0.1] = np.nan
    s = ScratchRows((7, 3))
    for lo in range(0, 1000, 333):  # blocks of any size, in order
        s.write(a[lo:lo + 333])
    assert s.written == 1000 and s.shape == a.shape and s.ndim == 3
    np.testing.assert_array_equal(s[:], a)
    np.testing.assert_array_equal(s[17:412], a[17:412])
    np.testing.assert_array_equal(s[990:2000], a[990:])  # a slice clipped as numpy clips it
    assert s[5:5].shape == (0, 7, 3)
    for rows in (np.array([3, 4, 5, 9, 2, 2, 999]), 42, -1, slice(0, 100, 7), (slice(3, 50), slice(2, 5)),
                 (7, 1), (np.array([4, 8]), slice(None), 2)):
        np.testing.assert_array_equal(s[rows], a[rows])
    mask = np.zeros(1000, bool)
    mask[[0, 5, 999]] = True
    np.testing.assert_array_equal(s[mask], a[mask])
    for bad in ((np.array([1, 2]), np.array([0, 2])), (Ellipsis, 0), 1000, np.array([[1, 2]]), np.array([1.5])):
        with pytest.raises(IndexError):  # not what numpy would give, or out of range: refused
            s[bad]
    with pytest.raises(TypeError):  # never made into the whole array implicitly
        np.asarray(s)
    flat = a.reshape(1000, 21)
    for cols in (slice(0, 21), slice(4, 11), slice(20, 21)):
        got = s.columns(cols)
        np.testing.assert_array_equal(got, flat[:, cols])
        assert got.flags.c_contiguous  # laid out as the array's rows: BLAS gives the same numbers
    with pytest.raises(IndexError):
        s.columns(slice(0, 21, 2))
    s.patch(500, np.zeros((7, 3)))  # a row replaced: rows and columns read it
    s.write(a[:10])  # more rows after columns were read
    b = np.concatenate([a, a[:10]])
    b[500] = 0.0
    np.testing.assert_array_equal(s[:], b)
    np.testing.assert_array_equal(s.columns(slice(2, 9)), b.reshape(1010, 21)[:, 2:9])
    with pytest.raises(IndexError):
        s.patch(1010, a[0])
    s.close()
    spilled = SpilledRows((4,), keep=8)
    rows = rng.normal(size=(100, 4))
    for r in rows:
        spilled.append(r)
    broken = ScratchRows((3,))  # a file shorter than its rows (a failing disk): an I/O error, one line
    broken.write(np.zeros((5, 3)))
    broken.written = 10
    with pytest.raises(OSError, match="scratch file .* is short") as err:
        broken[:]
    assert err.value.errno == errno.EIO
    empty = ScratchRows.of(np.zeros((5, 3, 0)))  # rows of no values (a truth without per-order envelopes)
    assert empty.shape == (5, 3, 0) and empty[1:4].shape == (3, 3, 0)
    copy = spilled.scratch(block=7)  # from the file and from memory, a block at a time
    np.testing.assert_array_equal(copy[:], rows)
    copy.close()
    spilled.close()


def test_sparse_rows_read_back_the_latest_row_written_and_zeros_elsewhere():
    """Rows written in any order, above and below the first index, some twice (in one write
    and across writes): every range reads what a dict index -> row gives, zeros elsewhere."""
    rng = np.random.default_rng(5)
    s = SparseRows((2, 3), np.float32)
    assert s.read(-4, 6).shape == (10, 2, 3) and not s.read(-4, 6).any()  # nothing written: zeros
    want: dict = {}
    for _ in range(12):
        index = rng.integers(-300, 300, size=rng.integers(1, 40))
        rows = rng.normal(size=(index.size, 2, 3)).astype(np.float32)
        s.write(index, rows)
        for i, r in zip(index.tolist(), rows):
            want[i] = r
    s.write([], np.zeros((0, 2, 3)))  # nothing
    for a, b in ((-400, 400), (-300, -299), (0, 1), (17, 180), (-120, 5), (250, 500), (5, 5), (9, 3)):
        expect = np.zeros((max(b - a, 0), 2, 3), np.float32)
        for i, r in want.items():
            if a <= i < b:
                expect[i - a] = r
        np.testing.assert_array_equal(s.read(a, b), expect)
    s.close()


def test_streaming_processor_state_is_bounded_and_gives_the_same_results(monkeypatch):
    from bttsim_stream.paper.validate_processing import simulate

    run = simulate()
    held = StreamingProcessor(run.info, ProcessOptions(window=3))
    outs_held = _stream_all(run, held, call_nsv=False)  # nothing released: every row held
    monkeypatch.setattr(history, "SPILL_BYTES", 64 * run.toa_s[0].nbytes)
    bounded = StreamingProcessor(run.info, ProcessOptions(window=3))
    outs = _stream_all(run, bounded, call_nsv=True)
    assert bounded._toa.spilled > run.opr_s.size - 200  # the TOAs in the scratch file
    assert bounded._d._a.shape[0] <= 256 < run.opr_s.size  # the live displacements: recent rows only
    assert len(outs) == len(outs_held) == run.opr_s.size
    for a, b in zip(outs, outs_held):
        for name in ("revolution", "opr_s", "omega_rad_s", "calibrated"):
            assert getattr(a, name) == getattr(b, name)
        for name in ("d_m", "amp_pkpk_m", "phase_rad", "amp_std_m", "dc_m", "residual_rms_m"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert bounded.finish(run.truth) == held.finish(run.truth)
    np.testing.assert_array_equal(bounded.result.opr_s, held.result.opr_s)


def test_truth_tracker_rows_spilled_are_the_latest_of_each_revolution(monkeypatch):
    """The tracker's per-revolution truth, spilled to its scratch file, reads back as a dict
    of the latest arrival per revolution would: out of order, repeated, other orders."""
    from bttsim_stream.process.resonance import TruthPeakTracker

    monkeypatch.setattr(history, "SPILL_BYTES", 200)
    rng = np.random.default_rng(7)
    nb = 5
    tr = TruthPeakTracker(8)
    ref_amp, ref_om, ref_eo = {}, {}, {}
    revs = list(range(3, 400)) + [50, 51, 399, 2, 1000]  # repeats, one earlier, one far out
    head = revs[:100]
    rng.shuffle(head)
    revs[:100] = head  # out of order
    for rev in revs:
        a, w = rng.random(nb), 300.0 + rng.random()
        orders = np.array([8, 9]) if rev != 51 else np.array([8, 10])
        own = rng.random((nb, 2))
        tr.update(rev, a, w, eo=(orders, own))
        ref_amp[rev], ref_om[rev], ref_eo[rev] = a, w, (orders, own)
    assert tr._rows.spilled > 0 and tr._eo[nb * 2].spilled > 0
    got = tr.rows(10, 395)
    for i in range(395):
        rev = 10 + i
        if rev in ref_amp:
            np.testing.assert_array_equal(got.d_eqv_pkpk_m[i], ref_amp[rev])
            assert got.omega_mean[i] == ref_om[rev]
            o, own = ref_eo[rev]
            want = own if np.array_equal(o, [8, 9]) else np.full((nb, 2), np.nan)  # the earliest's orders
            np.testing.assert_array_equal(got.eo_pkpk_m[i], want)
        else:
            assert np.isnan(got.d_eqv_pkpk_m[i]).all() and np.isnan(got.omega_mean[i])
    np.testing.assert_array_equal(got.eo_engine_order, [8, 9])
    early = TruthPeakTracker(8)
    early.update(1, np.ones(nb), 1.0, eo=(np.array([3]), np.ones((nb, 1))))
    early.update(0, np.ones(nb), 1.0, eo=(np.array([4]), np.full((nb, 1), 2.0)))
    rows = early.rows(0, 2)
    np.testing.assert_array_equal(rows.eo_engine_order, [4])  # revolution 0's orders, whatever came first
    assert rows.eo_pkpk_m[0, 0, 0] == 2.0 and np.isnan(rows.eo_pkpk_m[1]).all()
    mixed = TruthPeakTracker(8)  # tables of another number of orders than the first one's
    mixed.update(1, np.ones(nb), 1.0, eo=(np.array([8]), np.ones((nb, 1))))
    mixed.update(0, np.ones(nb), 1.0, eo=(np.array([8, 16]), np.full((nb, 2), 2.0)))
    mixed.update(2, np.ones(nb), 1.0, eo=(np.array([8, 16]), np.full((nb, 2), 3.0)))
    mixed.update(2, np.ones(nb), 1.0, eo=(np.array([8]), np.ones((nb, 1))))  # revolution 2 again: the later
    rows = mixed.rows(0, 3)
    np.testing.assert_array_equal(rows.eo_engine_order, [8, 16])
    assert (rows.eo_pkpk_m[0] == 2.0).all() and np.isnan(rows.eo_pkpk_m[1:]).all()


def test_a_long_gap_is_filled_before_its_rows_can_be_spilled(monkeypatch):
    """Lost revolutions are filled with missing arrivals; a gap longer than the TOAs kept in
    memory is worked through as it is filled, so no revolution is spilled before Eq. 1."""
    from bttsim_stream.paper.validate_processing import simulate

    run = simulate()
    skip = range(1500, 2300)

    def stream(proc):
        outs = []
        for n in range(run.opr_s.size):
            if n not in skip:
                outs += proc.push(n, run.opr_s[n], run.toa_s[n])
        return outs + proc.flush()

    held = stream(StreamingProcessor(run.info))
    monkeypatch.setattr(history, "SPILL_BYTES", 100 * run.toa_s[0].nbytes)
    bounded_proc = StreamingProcessor(run.info)
    bounded = stream(bounded_proc)
    assert bounded_proc._toa.spilled > 2300
    assert [o.revolution for o in bounded] == [o.revolution for o in held] == list(range(run.opr_s.size))
    for a, b in zip(bounded, held):
        np.testing.assert_array_equal(a.d_m, b.d_m)
        np.testing.assert_array_equal(a.amp_pkpk_m, b.amp_pkpk_m)
