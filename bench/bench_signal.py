"""Benchmark: cost of the probe signal chain per blade passage (prints JSON).

Usage::

    OMP_NUM_THREADS=1 python bench/bench_signal.py

For the default ``[acquisition.signal]`` (optical, 2 MS/s, 1 MHz bandwidth, 5 mV noise) and
for a capacitive probe, at 1000, 2500 and 4000 rpm on the default 0.19 m tip radius: CPU
microseconds per passage of :func:`~bttsim_stream.sim.signal.synthesise` and of
:func:`~bttsim_stream.sim.signal.apply_triggers` (4640 passages per call: a 32-revolution
batch of 29 blades and 5 probes), and the samples per window. Target (issue 14): the whole
default run with the chain on at >= 5x real time (783,000 passages in 130 s: <= 33 us per
passage including the simulation).
"""

from __future__ import annotations

import json
import math
import time

import numpy as np

from bttsim_stream.scenario import Signal
from bttsim_stream.sim.signal import Digitiser, ProbeModel, Trigger, apply_triggers, pulse_parameters, synthesise


def _case(kind: str, rpm: float, n: int = 4640, repeat: int = 3) -> dict:
    s = Signal()
    probe = ProbeModel(kind, s.spot_diameter_m if kind == "optical" else s.electrode_diameter_m, s.tip_thickness_m,
                       s.reference_clearance_m, s.height_v, s.fringe_factor, s.bandwidth_hz)
    dig = Digitiser(sample_rate_hz=s.sample_rate_hz, bits=s.bits, noise_v=s.noise_v)
    rng = np.random.default_rng(0)
    toa = 10.0 + np.sort(rng.uniform(0, 0.5, n))
    pp = pulse_parameters(probe, np.full(n, s.clearance_m), np.full(n, rpm * math.pi / 30 * 0.19))
    tau = np.full(n, probe.tau_s)
    pr = np.arange(n) % 5
    best_s, best_t = math.inf, math.inf
    for _ in range(repeat):
        t0 = time.process_time()
        win = synthesise(toa, pp, tau, pr, dig, rng)
        t1 = time.process_time()
        apply_triggers(win, [Trigger(s.trigger, s.level_v, s.hysteresis_v)] * 5, pr)
        t2 = time.process_time()
        best_s, best_t = min(best_s, t1 - t0), min(best_t, t2 - t1)
    return {"probe": kind, "rpm": rpm, "samples_per_window": int(win.n_samples.max()),
            "synthesise_us_per_passage": round(best_s / n * 1e6, 2),
            "trigger_us_per_passage": round(best_t / n * 1e6, 2)}


def main() -> None:
    cases = [_case(k, rpm) for k in ("optical", "capacitive") for rpm in (1000.0, 2500.0, 4000.0)]
    print(json.dumps({"bench": "signal_chain", "cases": cases}, indent=2))


if __name__ == "__main__":
    main()
