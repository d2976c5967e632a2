"""Print live blade times of arrival from a bttsim simulator (or any bttsim.v1 publisher).

Run ``python examples/subscribe_toas.py ENDPOINT [N] [--listen]``: connect to ENDPOINT (e.g.
``tcp/127.0.0.1:7447`` of a ``bttsim node sim -l ...``), or with ``--listen`` listen on it (for
``bttsim replay ... -e ENDPOINT``, which connects); stop after N batches if given.
"""
import sys
import threading

import zenoh

from bttsim_stream.bus import codec  # or build the classes from schemas/bttsim/v1/bttsim.proto

args = [a for a in sys.argv[1:] if a != "--listen"]
side = "listen" if "--listen" in sys.argv else "connect"
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5(f"{side}/endpoints", f'["{args[0]}"]')
with zenoh.open(conf) as session:
    sub = session.declare_subscriber("bttsim/*/toa/*", handler=zenoh.handlers.FifoChannel(1024))
    for i, sample in enumerate(sub):  # one ToaBatch per probe per revolution
        msg = codec.decode_toa_batch(sample.payload.to_bytes(), str(sample.key_expr))
        print(msg.header.revolution, msg.body.probe, msg.body.toa_s[:3], flush=True)
        if len(args) > 1 and i + 1 == int(args[1]):
            # optional: stop after N batches. A publisher may still be sending (it blocks rather
            # than drops): keep emptying the channel while the session closes, or zenoh's
            # receiving thread stays blocked on the full channel and the close times out
            threading.Thread(target=lambda: [None for _ in sub], daemon=True).start()
            break
