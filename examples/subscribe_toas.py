"""Print live blade times of arrival from a bttsim simulator (or any bttsim.v1 publisher)."""
import sys, zenoh
from bttsim_stream.io import codec          # or build the classes from schemas/bttsim/v1/bttsim.proto

conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("connect/endpoints", f'["{sys.argv[1]}"]')   # e.g. tcp/127.0.0.1:7447
with zenoh.open(conf) as session:
    sub = session.declare_subscriber("bttsim/*/toa/*", handler=zenoh.handlers.FifoChannel(1024))
    for i, sample in enumerate(sub):         # one ToaBatch per probe per revolution
        msg = codec.decode_toa_batch(sample.payload.to_bytes(), str(sample.key_expr))
        print(msg.header.revolution, msg.probe, msg.toa_s[:3], flush=True)
        if len(sys.argv) > 2 and i + 1 == int(sys.argv[2]):
            break                            # optional: stop after N batches
