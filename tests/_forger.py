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
"""

import argparse
import json
import sys
import time

import zenoh

from bttsim_stream.acquisition import AcquisitionStream
from bttsim_stream.bus.security import tls_from_args
from bttsim_stream.bus.session import StopFlag, make_config, open_session, pack_attachment
from bttsim_stream.errors import exit_status
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


def main(args) -> None:
    forged = [f for f in forged_messages(args.scenario)
              if not args.only or any(f[0].endswith("/" + k) for k in args.only)]
    conf = make_config("client", args.connect, tls=tls_from_args(args, "intruder"),
                       connect_timeout_s=args.connect_timeout)
    stop = StopFlag()
    put = matched = 0
    with open_session(conf) as session:
        print("forger connected", flush=True)
        rig = forged[0][0].split("/")[1]
        token = session.liveliness().declare_token(f"bttsim/{rig}/alive/sim") if args.pose_as_sim else None
        pubs = {k: session.declare_publisher(k, congestion_control=zenoh.CongestionControl.DROP)
                for k in dict.fromkeys(k for k, _, _ in forged)}
        while not stop:
            for key, payload, seq in forged:
                time.sleep(PERIOD_S)  # not stop.wait: a signal during Event.wait can deadlock its handler
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
    sys.exit(exit_status(main, p.parse_args()))
