"""The message stream: sequence numbers, results to messages, revolution assembly."""

import dataclasses

import numpy as np
import pytest

from bttsim_stream.bus import codec, keys
from bttsim_stream.bus.stream import MessageStream, RevolutionAssembler, SequenceTracker, Sequencer
from bttsim_stream.process.options import ProcessOptions
from bttsim_stream.process.streaming import StreamingProcessor

from _io_helpers import NB, NP, NR, make_batch, make_info

pytestmark = pytest.mark.unit


def test_sequencer_counts_per_key():
    s = Sequencer()
    assert [s.next("a"), s.next("a"), s.next("b"), s.next("a")] == [0, 1, 0, 2]
    assert (s.count("a"), s.count("b"), s.count("c")) == (3, 1, 0)


def test_sequence_numbers_count_per_key_across_batches():
    stream = MessageStream("r", "rig1")
    msgs = stream.acquisition(make_batch(seed=1)) + stream.acquisition(make_batch(seed=2, rev0=NR))
    by_key = {}
    for m in msgs:
        h = codec.decode_message(m.key, m.payload).header
        assert h.seq == m.seq  # the record and the header agree
        by_key.setdefault(m.key, []).append(h)
    assert set(by_key) == {"bttsim/rig1/opr", "bttsim/rig1/truth", *(f"bttsim/rig1/toa/{j}" for j in range(NP))}
    for key, headers in by_key.items():
        assert [h.seq for h in headers] == list(range(2 * NR)), key
        assert [h.revolution for h in headers] == list(range(2 * NR)), key


def test_run_metadata_message_has_the_stream_run_id():
    m = MessageStream("run-x", "rig1").run_metadata(make_info(run_id="other"))
    d = codec.decode_run_metadata(m.payload, m.key)
    assert (m.key, m.seq, m.log_time_ns) == ("bttsim/rig1/meta", 0, 0)
    assert d.body.run_id == d.header.run_id == "run-x"


def _outputs(n_rev=12, eos=(8, 9)):
    """Real streaming outputs of a rigid rotor at constant speed (five probes, two EOs)."""
    info = make_info(engine_orders=eos, nodal_diameters=(1,) * len(eos))
    proc = StreamingProcessor(info, ProcessOptions(calibration=None))
    period = 0.02
    opr = period * np.arange(n_rev)
    psi = np.mod(info.probe_angles_rad[None, :] - 2 * np.pi * np.arange(NB)[:, None] / NB - info.opr_angle_rad,
                 2 * np.pi)
    out = []
    for k in range(n_rev):
        out += proc.push(k, opr[k], opr[k] + psi / (2 * np.pi) * period)
    return out + proc.flush()


def test_processing_messages_one_fit_per_engine_order_then_one_wave_per_probe():
    outs = _outputs()
    stream = MessageStream("r", "rig1")
    msgs = stream.processing(outs[0])
    assert [m.key for m in msgs] == ["bttsim/rig1/fit"] * 2 + [f"bttsim/rig1/tw/{j}" for j in range(NP)]
    fits = [codec.decode_fit(m.payload, m.key).body for m in msgs[:2]]
    assert [f.engine_order for f in fits] == [8, 9]
    np.testing.assert_array_equal(fits[1].amp_pkpk_m, outs[0].amp_pkpk_m[:, 1])
    assert [m.seq for m in msgs[:2]] == [0, 1]
    waves = [codec.decode_probe_wave(m.payload, m.key).body for m in msgs[2:]]
    assert [w.probe for w in waves] == list(range(NP))
    assert {w.nd for w in waves} == {int(outs[0].fit_tw.dominant_nd)}
    # a rigid rotor at the nominal geometry: no vibration at all
    assert np.nanmax(np.abs(fits[0].amp_pkpk_m)) < 1e-12
    later = stream.processing(outs[1])
    assert [m.seq for m in later if m.key.endswith("/fit")] == [2, 3]


def _fragments(n_rev=5, drop=()):
    """Decoded OPR / TOA fragments of ``n_rev`` revolutions, minus ``(kind, revolution, probe)``."""
    batch = make_batch(seed=9, nr=n_rev)
    out = []
    for m in MessageStream("r", "rig1").acquisition(batch, include_truth=False):
        kind = m.key.split("/")[2]
        d = codec.decode_message(m.key, m.payload)
        probe = d.body.probe if kind == "toa" else None
        if (kind, d.header.revolution, probe) not in drop:
            out.append((kind, d))
    return batch, out


def _interleave(frags, lag, seed=0):
    """The fragments as a receiver sees them: each source (the OPR stream, each probe's
    stream) in its own order, the sources drifting up to ``lag`` revolutions apart."""
    rng = np.random.default_rng(seed)

    def src(kd):
        return -1 if kd[0] == "opr" else kd[1].body.probe

    n = 1 + max(d.header.revolution for _, d in frags)
    sources = sorted({src(f) for f in frags})
    offsets = np.linspace(0.0, lag, len(sources))[rng.permutation(len(sources))]
    delay = {s: o + rng.uniform(0.0, 5.0, size=n) for s, o in zip(sources, offsets)}
    t = [d.header.revolution + delay[src((k, d))][d.header.revolution] for k, d in frags]
    for s in delay:  # one source's messages stay in order
        idx = [i for i, f in enumerate(frags) if src(f) == s]
        for i, ti in zip(idx, np.maximum.accumulate([t[i] for i in idx])):
            t[i] = ti
    return [frags[i] for i in np.argsort(t, kind="stable")]


def test_assembler_gives_complete_revolutions_in_order_despite_sources_far_apart():
    """The OPR stream and the probes' streams drift up to 300 revolutions apart (measured on a
    loaded machine: 257): every revolution still comes out whole, in order."""
    batch, frags = _fragments(n_rev=400)
    mixed = _interleave(frags, lag=300.0)
    assert max(abs(a[1].header.revolution - b[1].header.revolution) for a, b in zip(mixed, mixed[1:])) > 250
    asm = RevolutionAssembler(NB, NP, n_revolutions=400)
    got = []
    for kind, d in mixed:
        asm.add(kind, d)
        got += asm.pop()
    assert asm.pending == 0
    got += asm.pop(final=True)
    assert [r.revolution for r in got] == list(range(400))
    assert all(r.complete for r in got) and asm.ignored == 0
    for r in got:
        np.testing.assert_array_equal(r.toa_s, batch.toa_s[r.revolution])
        assert r.opr_s == batch.opr_s[r.revolution]


def test_assembler_gives_out_an_incomplete_revolution_once_the_missing_source_has_moved_on():
    batch, frags = _fragments(drop={("toa", 1, 3)})
    asm = RevolutionAssembler(NB, NP)
    released = {}
    for kind, d in frags:
        asm.add(kind, d)
        for r in asm.pop():
            released[r.revolution] = (r, kind, d.header.revolution, d.body.probe if kind == "toa" else None)
    r1, kind, at, probe = released[1]
    assert not r1.complete and (kind, at, probe) == ("toa", 2, 3)  # probe 3's next batch: nothing more for 1
    assert np.isnan(r1.toa_s[:, 3]).all()
    np.testing.assert_array_equal(r1.toa_s[:, :3], batch.toa_s[1, :, :3])
    assert released[2][0].complete


def test_assembler_does_not_wait_forever_for_a_silent_probe():
    """A probe that never publishes: revolutions come out incomplete once ``reorder`` wait."""
    _, frags = _fragments(n_rev=30, drop={("toa", r, 2) for r in range(30)})
    asm = RevolutionAssembler(NB, NP, reorder=8)
    got = []
    for kind, d in frags:
        asm.add(kind, d)
        got += asm.pop()
        assert asm.pending <= 9
    assert len(got) >= 21 and not any(r.complete for r in got)


def test_assembler_drops_revolutions_without_opr_and_ignores_late_or_foreign_fragments():
    _, frags = _fragments(drop={("opr", 2, None)})
    asm = RevolutionAssembler(NB, NP)
    got = []
    for kind, d in frags:
        asm.add(kind, d)
        got += asm.pop()
    got += asm.pop(final=True)
    assert [r.revolution for r in got] == [0, 1, 3, 4] and asm.dropped == 1
    asm.add_opr(1, 123.0)  # already given out
    asm.add_toa(9, NP, np.zeros(NB))  # no such probe
    asm.add_toa(9, 0, np.zeros(NB + 1))  # wrong blade count
    assert asm.ignored == 3 and asm.pending == 0


def test_sequence_tracker_counts_duplicates_and_gaps():
    t = SequenceTracker()
    accepted = [t.accept("a", s) for s in (0, 1, 1, 0, 4, 5)] + [t.accept("b", 3), t.accept("c", None)]
    assert accepted == [True, True, False, False, True, True, True, True]
    assert t.duplicates == 2 and t.lost == 2 and t.gaps == {"a": 2}
    s = t.summary()
    assert s["messages"] == 6 and s["keys"] == 3 and s["late_start_keys"] == {"b": 3}


def test_assembler_rejects_forged_fragments_without_disturbing_the_run():
    batch, frags = _fragments(n_rev=6)
    asm = RevolutionAssembler(NB, NP, n_revolutions=6, max_ahead=8)
    got = []
    for i, (kind, d) in enumerate(frags):
        asm.add(kind, d)
        if i == 10:  # forgeries in the middle of the stream
            asm.add_opr(100_000, 1e3)  # far ahead: would flush everything in progress
            asm.add_opr(5, 1.0)  # within the run: accepted, later a duplicate of the real one
            asm.add_toa(1, 0, np.full(NB, 7.0))  # a second batch of a probe already in
            asm.add_opr(2, np.nan)
        got += asm.pop()
    got += asm.pop(final=True)
    assert [r.revolution for r in got] == list(range(6)) and all(r.complete for r in got)
    np.testing.assert_array_equal(np.stack([r.toa_s for r in got[:5]]), batch.toa_s[:5])
    assert asm.ignored == 2 and asm.duplicates == 2  # the real OPR 5 came second: a duplicate


def test_sequence_tracker_does_not_believe_a_far_jump():
    """A forged number far ahead would make every later message a duplicate: it is refused."""
    t = SequenceTracker(max_jump=100)
    assert [t.accept("a", s) for s in (0, 1, 10**6, 2, 3, 50)] == [True, True, False, True, True, True]
    assert (t.implausible, t.duplicates, t.lost) == (1, 0, 46)


def test_sequence_tracker_missing_head_gaps_and_tail_per_key():
    """Against the run's known counts: the numbers before the first received, between, and
    after the last up to n-1; a key with nothing received misses all of it; a key of unknown
    count (a result key) is checked for head and gaps only."""
    t = SequenceTracker()
    t.expect({"opr": 10, "toa/0": 10, "toa/1": 10, "truth": 10})
    for s in (3, 4, 6, 7):  # head 0-2, gap 5, tail 8-9
        t.accept("opr", s)
    for s in range(10):  # whole
        t.accept("toa/0", s)
    for s in (2, 5, 9):  # a result key: head 2, gaps 2 + 3, tail unknown
        t.accept("fit", s)
    got = {k: m.to_dict() for k, m in t.missing({"opr": 10, "toa/0": 10, "toa/1": 10, "truth": 10}).items()}
    assert got == {"opr": {"head": 3, "gaps": 1, "tail": 2}, "toa/1": {"head": 10, "gaps": 0, "tail": 0},
                   "truth": {"head": 10, "gaps": 0, "tail": 0}, "fit": {"head": 2, "gaps": 5, "tail": 0}}
    assert t.missing({"toa/0": 10}).keys() == {"opr", "fit"}  # toa/0 whole


def test_sequence_tracker_bounds_forged_numbers_by_the_known_count():
    """A forged number at or beyond a key's known count, or (unknown count) a first number
    beyond max_jump, is not believed: the counts stay within the run and the real stream is
    still accepted."""
    t = SequenceTracker(max_jump=100)
    t.expect({"opr": 5})
    assert [t.accept("opr", s) for s in (10**18, 5, 0, 1, 2, 3, 4, 5)] == [False] * 2 + [True] * 5 + [False]
    assert [t.accept("fit", s) for s in (10**18, 101, 0)] == [False, False, True]
    assert t.implausible == 5 and t.missing({"opr": 5}) == {}
    assert t.accept("tw", 100) and t.missing()["tw"].to_dict() == {"head": 100, "gaps": 0, "tail": 0}


@pytest.mark.parametrize("truth", [True, False], ids=["truth", "blind"])
def test_acquisition_counts_are_the_published_stream(truth):
    """The counts the recorder checks against are exactly what a publisher numbers for a run."""
    from bttsim_stream.bus.stream import acquisition_counts

    info = make_info(n_revolutions=NR, has_truth=truth)
    stream = MessageStream("run", "rig1")
    msgs = [stream.run_metadata(info)] + stream.acquisition(make_batch(), include_truth=truth)
    t = SequenceTracker()
    for m in msgs:
        t.accept(m.key, m.seq)
    counts = acquisition_counts(info)
    assert counts == {k: stream.sequencer.count(k) for k in counts} and len(counts) == NP + 2 + truth
    assert t.missing(counts) == {}
    assert {k: m.total for k, m in t.missing(dict(counts, **{keys.opr_key("rig1"): NR + 4})).items()} == \
        {keys.opr_key("rig1"): 4}


def _reference_acquisition(stream, batch, include_truth=True):
    """The acquisition messages encoded one at a time with the per-message encoders, numbered by
    the stream's sequencer (what MessageStream.acquisition produced before it encoded batches)."""
    from bttsim_stream.bus import keys
    from bttsim_stream.bus.stream import Message

    out = []
    toa = np.asarray(batch.toa_s)
    nr, nb, npr = toa.shape

    def msg(key, rev, t, encode, *args):
        seq = stream.sequencer.next(key)
        return Message(key, encode(codec.Header(stream.run_id, seq, rev, t), *args), codec.log_time_ns(t), seq)

    for i in range(nr):
        rev, t_opr = int(batch.revolution[i]), float(batch.opr_s[i])
        ticks = None if batch.opr_ticks is None else int(batch.opr_ticks[i])
        out.append(msg(keys.opr_key(stream.rig), rev, t_opr, codec.encode_opr, codec.OprPulse(t_opr, ticks)))
        for j in range(npr):
            col = toa[i, :, j]
            latest = float(np.fmax.reduce(col)) if not np.all(np.isnan(col)) else t_opr
            tt = None if batch.toa_ticks is None else batch.toa_ticks[i, :, j].tolist()
            out.append(msg(keys.toa_key(stream.rig, j), rev, latest, codec.encode_toa_batch, j, col.tolist(), tt))
        if include_truth:
            out.append(msg(keys.truth_key(stream.rig), rev, t_opr, codec.encode_truth, batch.truth, i))
    return out


@pytest.mark.parametrize("ticks", [False, True], ids=["float-clock", "ticks"])
@pytest.mark.parametrize("include_truth", [True, False], ids=["truth", "blind"])
def test_acquisition_is_the_message_by_message_encoding(ticks, include_truth):
    a, b = MessageStream("run-a", "rig1"), MessageStream("run-a", "rig1")
    for seed, rev0 in ((1, 0), (2, NR)):
        batch = make_batch(seed=seed, ticks=ticks, rev0=rev0)
        toa = batch.toa_s.copy()
        toa[0, :, 1] = np.nan  # a probe that saw nothing: its header time is the OPR
        toa[1, 2, 0] = np.nan
        batch = type(batch)(**{f: getattr(batch, f) for f in batch.__dataclass_fields__ if f != "toa_s"}, toa_s=toa)
        got = a.acquisition(batch, include_truth=include_truth)
        assert got == _reference_acquisition(b, batch, include_truth)


def test_processor_session_refuses_messages_of_another_run_before_they_take_a_number():
    """A forger who knows the next sequence numbers but not the run: its TOA batch and truth
    are refused and counted, the real messages with those numbers are kept, and the result is
    the clean one, bit for bit."""
    from bttsim_stream.acquisition import AcquisitionStream
    from bttsim_stream.processor import ProcessorSession
    from bttsim_stream.scenario import Scenario, Speed

    acq = AcquisitionStream(Scenario(speed=Speed(start_rpm=2400.0, end_rpm=2800.0, duration_s=12.0)))
    msgs = [m for _, ms in acq.batches() for m in ms]
    meta = codec.decode_message(acq.meta.key, acq.meta.payload).body

    def run(messages):
        s = ProcessorSession(meta)
        for m in messages:
            kind = m.key.split("/")[2]
            s.add(kind, m.key, codec.decode_message(m.key, m.payload), m.seq)
        assert s.received_all
        return s, s.finish()[1]

    _, clean = run(msgs)
    i = next(k for k, m in enumerate(msgs) if m.key.endswith("/toa/0") and m.seq == 5)
    j = next(k for k, m in enumerate(msgs) if m.key.endswith("/truth") and m.seq == 300)
    d, t = codec.decode_message(msgs[i].key, msgs[i].payload), codec.decode_message(msgs[j].key, msgs[j].payload)
    toa = codec.encode_toa_batch(codec.Header("forged", 5, 5, d.header.t_s), 0, (d.body.toa_s + 1e-6).tolist())
    truth = codec.encode_truth(codec.Header("forged", 300, 300, t.header.t_s),
                               dataclasses.replace(t.body, d_eqv_pkpk_m=t.body.d_eqv_pkpk_m * 10))
    forged = (msgs[:i] + [msgs[i].__class__(msgs[i].key, toa, msgs[i].log_time_ns, 5)] + msgs[i:j]
              + [msgs[j].__class__(msgs[j].key, truth, msgs[j].log_time_ns, 300)] + msgs[j:])
    s, got = run(forged)
    assert got["rejected"] == 2 and got["duplicates"] == 0 and got["complete"]
    assert got["blades"] == clean["blades"] and got["resonances"] == clean["resonances"]



@pytest.mark.parametrize("where", ["first", "middle", "last"])
def test_processor_session_refuses_a_toa_outside_its_revolution_as_a_recording_would_be(where):
    """The rule by which ``bttsim process`` refuses a recording (a TOA neither NaN nor within
    ``[opr - T, opr + 2 T]`` of its OPR pulse, ``T`` the revolution's period) holds live too:
    the forged batch is dropped before the final report, counted as rejected and lost, and the
    result is not called complete. Just inside the bounds nothing is refused."""
    from bttsim_stream.acquisition import AcquisitionStream
    from bttsim_stream.processor import ProcessorSession
    from bttsim_stream.scenario import Scenario, Speed

    acq = AcquisitionStream(Scenario(speed=Speed(start_rpm=2400.0, end_rpm=2800.0, duration_s=6.0)))
    msgs = [m for _, ms in acq.batches() for m in ms]
    meta = codec.decode_message(acq.meta.key, acq.meta.payload).body
    opr = np.array([codec.decode_opr(m.payload).body.opr_s for m in msgs if m.key.endswith("/opr")])
    n = opr.size
    rev = {"first": 0, "middle": n // 2, "last": n - 1}[where]
    period = opr[rev + 1] - opr[rev] if rev + 1 < n else opr[rev] - opr[rev - 1]

    def run(toa_value):
        s = ProcessorSession(meta)
        for m in msgs:
            d = codec.decode_message(m.key, m.payload)
            if m.key.endswith("/toa/2") and m.seq == rev:
                toa = d.body.toa_s.copy()
                toa[5] = toa_value
                d = codec.decode_message(m.key, codec.encode_toa_batch(d.header, 2, toa.tolist()))
            s.add(m.key.split("/")[2], m.key, d, m.seq)
        return s.finish()[1]

    for inside in (opr[rev] - 0.999 * period, opr[rev] + 1.999 * period):
        got = run(inside)
        assert got["complete"] and got["rejected"] == 0 and got["lost"] == 0
    for outside in (opr[rev] - 1.001 * period, opr[rev] + 2.001 * period, 1e300, -1e300):
        with np.errstate(all="raise"):  # the forged value never reaches the arithmetic
            got = run(outside)
        assert not got["complete"] and got["rejected"] == 1 and got["lost"] == 1
        assert got["revolutions_processed"] == n
