"""CPU cost of the recorder's checks (RecordGate): every message of a run decoded and judged.

``python bench/bench_record_gate.py [SCENARIO.toml]`` prints one JSON line: messages, CPU
seconds, microseconds per message, for the real stream and for a flood of garbage.
"""

import json
import os
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

from bttsim_stream.acquisition import AcquisitionStream  # noqa: E402
from bttsim_stream.bus.admission import RecordGate  # noqa: E402
from bttsim_stream.scenario import Scenario, load_scenario  # noqa: E402


def main() -> None:
    scn = load_scenario(sys.argv[1]) if len(sys.argv) > 1 else Scenario()
    acq = AcquisitionStream(scn, include_truth=True)
    msgs = [acq.meta] + [m for _, ms in acq.batches() for m in ms]
    gate = RecordGate(acq.rig)
    t0 = time.process_time()
    for m in msgs:
        gate.admit(m.key, m.payload, (m.seq, m.log_time_ns), "sim")
    real_s = time.process_time() - t0
    assert gate.missing() == {} and gate.rejected == 0
    n_flood = 100_000
    t0 = time.process_time()
    for i in range(n_flood):
        gate.admit(f"bttsim/{acq.rig}/fit", b"\x0a\x02zz" + i.to_bytes(8, "little"), (i, i), "forger")
    flood_s = time.process_time() - t0
    print(json.dumps({"messages": len(msgs), "cpu_s": round(real_s, 3),
                      "us_per_message": round(1e6 * real_s / len(msgs), 1), "flood_messages": n_flood,
                      "flood_us_per_message": round(1e6 * flood_s / n_flood, 1)}))


if __name__ == "__main__":
    main()
