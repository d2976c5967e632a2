"""A forger for the security tests: a Zenoh client that floods a rig with forged messages.

``python tests/_forger.py SCENARIO -e ENDPOINT [--tls-dir DIR --tls-name NAME]``: the
scenario's real acquisition messages (metadata, OPR, TOA batches, truth) with the payload of a
revolution 50 later on each key and sequence number, TOA batches on a probe that does not
exist (``toa/7``), garbage on the result keys (fit, travelling wave, resonance), and (``--pose-as-sim``) a
liveliness token posing as the simulator; ``--only toa/7`` keeps the keys so named; ``--once`` puts
each message once, as soon as its key has a subscriber (a flood that never stops keeps the
consumers from ever seeing the end of a run). Prints ``forger connected`` once its session is
open, then puts a message every 10 ms until SIGTERM, and finally one JSON line:
how many messages it put and how many of them while a subscriber matched (they would have
been delivered without access control). A session that cannot be opened (refused) is the
one-line error of every node, exit 2.

The forgeries of a run without security: ``--garbage N`` puts N garbage payloads on the TOA
keys (with ``--once``: once through); ``--next KEY`` answers every real message on KEY with
garbage and a well-formed batch for the next number, at once (racing the real one);
``--flood KEY --rate R --seconds S`` floods KEY from its first subscriber on.
"""

import argparse
import json
import queue
import random
import sys
import time

import zenoh

from bttsim_stream.acquisition import AcquisitionStream
from bttsim_stream.bus.security import tls_from_args
from bttsim_stream.bus import codec
from bttsim_stream.bus.session import StopFlag, make_config, open_session, pack_attachment, unpack_attachment
from bttsim_stream.errors import BttsimError, exit_status
from bttsim_stream.scenario import load_scenario

SHIFT = 50  # revolutions
PERIOD_S = 0.01  # between two puts: a flood would only load the machine (and the router)


def forged_messages(scenario_path: str) -> list[tuple[str, bytes, int]]:
    acq = AcquisitionStream(load_scenario(scenario_path), include_truth=True)
    msgs = [acq.meta] + [m for _, ms in acq.batches() for m in ms]
    by_key: dict[str, list] = {}
    for m in msgs:
        by_key.setdefault(m.key, []).append(m)
    out = []
    for key, ms in by_key.items():
        for i, m in enumerate(ms[:-SHIFT] if len(ms) > SHIFT else ms):
            out.append((key, ms[min(i + SHIFT, len(ms) - 1)].payload, m.seq))
    rig = acq.rig
    toa0 = by_key[f"bttsim/{rig}/toa/0"]
    out += [(f"bttsim/{rig}/toa/7", m.payload, m.seq) for m in toa0[:100]]
    out += [(f"bttsim/{rig}/{k}", b"\x08\x96\x01garbage", s) for s in range(100) for k in ("fit", "tw/0", "resonance")]
    out.sort(key=lambda t: t[2])  # interleaved like a live stream
    return out


def garbage_messages(scenario_path: str, n: int) -> list[tuple[str, bytes, int]]:
    """``n`` garbage payloads on the run's TOA keys (a probe each in turn), numbered through
    the run's sequence numbers: random bytes, truncated real batches, a protobuf of the
    wrong type."""
    acq = AcquisitionStream(load_scenario(scenario_path), include_truth=False)
    rng = random.Random(1)
    real = [m for _, ms in acq.batches() for m in ms if "/toa/" in m.key]
    out = []
    for i in range(n):
        key = f"bttsim/{acq.rig}/toa/{i % acq.info.n_probes}"
        seq = (i * 7) % acq.info.n_revolutions
        kind = i % 3
        if kind == 0:
            payload = bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 200)))
        elif kind == 1:
            m = real[i % len(real)]
            payload = m.payload[: rng.randint(1, len(m.payload) - 1)]
        else:
            payload = acq.meta.payload  # a RunMetadata where a ToaBatch belongs
        out.append((key, payload, seq))
    return out


def forged_next(key: str, payload: bytes, seq: int, t_ns: int) -> list[tuple[bytes, int, int]]:
    """What the ``--next`` forger puts on ``key`` once the real message ``seq`` is seen: for the
    next number, garbage and a well-formed batch (header, revolution, time all one revolution
    on, the TOAs shifted by one period): (payload, seq, t_ns)."""
    d = codec.decode_message(key, payload)
    h, b = d.header, d.body
    period = 60.0 / 2400.0
    t_s = h.t_s + period
    valid = codec.encode_toa_batch(codec.Header(h.run_id, seq + 1, h.revolution + 1, t_s), b.probe,
                                   (b.toa_s + period + 1e-4).tolist())
    return [(b"\x0a\x03abc" + bytes(8), seq + 1, t_ns + int(period * 1e9)),
            (valid, seq + 1, codec.log_time_ns(t_s))]


def run_next(session, args, stop) -> dict:
    """``--next KEY``: forge the next number of each real message on KEY, as soon as it is seen."""
    pub = session.declare_publisher(args.next, congestion_control=zenoh.CongestionControl.BLOCK)  # all counted
    out = queue.Queue()

    def on_sample(sample) -> None:
        att = unpack_attachment(sample.attachment)
        if att is not None and sample.timestamp is not None and str(sample.timestamp.get_id()) != str(session.zid()):
            out.put((str(sample.key_expr), sample.payload.to_bytes(), att))

    sub = session.declare_subscriber(args.next, on_sample)
    put = 0
    while not stop:
        try:
            key, payload, (seq, t_ns) = out.get(timeout=0.05)
        except queue.Empty:
            continue
        try:  # the other forgers' garbage comes in too
            answers = forged_next(key, payload, seq, t_ns)
        except BttsimError:
            continue
        for forged, fseq, ft in answers:
            pub.put(forged, attachment=pack_attachment(fseq, ft))
            put += 1
    sub.undeclare()
    return {"put": put, "matched": put}


def run_flood(session, args, stop) -> dict:
    """``--flood KEY``: ``--rate`` messages a second on KEY for ``--seconds`` (garbage; with
    ``--copies`` also re-sent copies of the key's real messages under other numbers), from the
    first match."""
    pub = session.declare_publisher(args.flood, congestion_control=zenoh.CongestionControl.DROP)
    seen: list = []
    while not stop and not pub.matching_status.matching:  # before a subscriber of its own matches it
        time.sleep(0.01)
    sub = session.declare_subscriber(args.flood, lambda s: args.copies and len(seen) < 100 and
                                     seen.append(s.payload.to_bytes()))
    put = 0
    t0 = time.monotonic()
    while not stop and time.monotonic() - t0 < args.seconds:
        due = int((time.monotonic() - t0) * args.rate)
        while put < due:
            payload = seen[put % len(seen)] if seen and put % 2 else b"\x0a\x02zz" + put.to_bytes(8, "little")
            pub.put(payload, attachment=pack_attachment(put, put * 1000))
            put += 1
        time.sleep(0.001)
    sub.undeclare()
    while not stop:  # then wait for the end
        time.sleep(0.05)
    return {"put": put, "matched": put}


def main(args) -> None:
    if args.next or args.flood:
        conf = make_config("client", args.connect, connect_timeout_s=args.connect_timeout)
        stop = StopFlag()
        with open_session(conf) as session:
            print("forger connected", flush=True)
            stats = (run_next if args.next else run_flood)(session, args, stop)
        print(json.dumps(stats), flush=True)
        return
    forged = [f for f in (garbage_messages(args.scenario, args.garbage) if args.garbage
                          else forged_messages(args.scenario))
              if not args.only or any(f[0].endswith("/" + k) for k in args.only)]
    conf = make_config("client", args.connect, tls=tls_from_args(args, "intruder"),
                       connect_timeout_s=args.connect_timeout)
    stop = StopFlag()
    put = matched = 0
    with open_session(conf) as session:
        print("forger connected", flush=True)
        rig = forged[0][0].split("/")[1]
        token = session.liveliness().declare_token(f"bttsim/{rig}/alive/sim") if args.pose_as_sim else None
        # the counted garbage (and each message of --once) must all reach the recorder: a queue
        # full of real 7 kB truth batches on the router's link to it would drop DROP messages
        congestion = zenoh.CongestionControl.BLOCK if args.garbage or args.once else zenoh.CongestionControl.DROP
        pubs = {k: session.declare_publisher(k, congestion_control=congestion)
                for k in dict.fromkeys(k for k, _, _ in forged)}
        while not stop:
            for key, payload, seq in forged:
                time.sleep(args.period)  # not stop.wait: a signal during Event.wait can deadlock its handler
                while args.once and not stop and not pubs[key].matching_status.matching:
                    time.sleep(0.01)
                if stop:
                    break
                pub = pubs[key]
                pub.put(payload, attachment=pack_attachment(seq, 0))
                put += 1
                matched += bool(pub.matching_status.matching)
            while args.once and not stop:  # once through, then wait for the end
                time.sleep(0.05)
        if token is not None:
            token.undeclare()
    print(json.dumps({"put": put, "matched": matched}), flush=True)


if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("scenario")
    p.add_argument("-e", "--connect", action="append", required=True)
    p.add_argument("--connect-timeout", type=float, default=5.0)
    p.add_argument("--tls-dir")
    p.add_argument("--tls-name")
    p.add_argument("--pose-as-sim", action="store_true")
    p.add_argument("--once", action="store_true", help="each message once, as soon as its key has a subscriber")
    p.add_argument("--only", action="append", metavar="KEY", help="only the keys ending in /KEY (e.g. toa/7)")
    p.add_argument("--garbage", type=int, metavar="N", help="N garbage messages on the TOA keys instead")
    p.add_argument("--next", metavar="KEY", help="forge the next number of every real message on KEY")
    p.add_argument("--flood", metavar="KEY", help="flood KEY at --rate messages a second for --seconds")
    p.add_argument("--period", type=float, default=PERIOD_S, help="seconds between two puts (0.01)")
    p.add_argument("--rate", type=float, default=10000.0)
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--copies", action="store_true",
                   help="--flood: every other message a copy of a real one on the key, under another number")
    sys.exit(exit_status(main, p.parse_args()))
