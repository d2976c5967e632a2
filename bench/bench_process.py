"""Benchmark: processing throughput, offline and streaming, on one core (prints JSON).

Usage::

    python bench/bench_process.py               # default run (HP), best of 3
    python bench/bench_process.py --method PAD --repeat 5
    python bench/bench_process.py --validate    # also bttsim validate --processing's processing

Simulates the default scenario once (not timed), then times

* offline ``process_arrays`` on the whole run: the default pipeline (OPR-based expected
  times, data preparation) and without data preparation;
* the streaming processor: one ``push`` per revolution (fits and travelling-wave spectra per
  revolution, and the live non-synchronous vibration scan of each completed block of
  revolutions, ``nsv_ready``) plus ``flush``; then ``finish`` (the final report over the
  history);

and, with ``--validate``, the processing of ``bttsim validate --processing`` as its test
runs it (no AD column, no probe angle errors: 18 whole-run ``process_arrays`` calls, each with
the swept SDOF fit of the zeroing check) on runs simulated beforehand;

and reports TOAs per CPU second (user + system; the machine is shared, wall time would
measure the neighbours) and the streaming latency in revolutions (revolution pushed when an
output appeared minus the output's revolution).

``streaming_engine_stage``: the same streaming processor on one stage of the target's shape,
60 blades x 16 probes (960 TOAs per revolution; a 20 s run-up of the default wheel with 60
blades), with the CPU share of one core that 10 such stages at 15,000 rpm (250 revolutions
per second each, 2.4e6 TOA/s) would take. The default run has 145 TOAs per revolution, so its
TOA rate measures the per-revolution cost; the engine stage's, the per-TOA cost.

Targets on one core: offline >= 1e6 TOA/s; streaming >= 2.4e6 TOA/s, a whole engine's BTT
(10 stages x 16 probes x 60 blades at 15,000 rpm).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")


#: One compressor stage of the target engine: 60 blades, 16 probes (a 20 s run-up).
ENGINE_STAGE = {"rotor": {"n_blades": 60},
                "probes": {"angles_deg": [5.0, 10.6, 15.15, 23.82, 40.0, 70.0, 100.0, 148.5, 190.35, 202.11, 220.0,
                                          245.0, 255.6, 280.0, 301.5, 330.0]},
                "speed": {"duration_s": 20.0}}


def _best(fn, repeat: int) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.process_time()
        out = fn()
        best = min(best, time.process_time() - t0)
    return best, out


def _validate_cpu(repeat: int) -> dict:
    """CPU seconds of ``validate(include_ad=False, include_probe_errors=False)``, its runs
    simulated (and cached) by a first, untimed call."""
    from bttsim_stream.paper.validate_processing import validate

    validate(include_ad=False, include_probe_errors=False)
    cpu, v = _best(lambda: validate(include_ad=False, include_probe_errors=False), repeat)
    return {"cpu_s": round(cpu, 3), "all_ok": bool(v["all_ok"])}


def main(method: str = "HP", repeat: int = 3, with_validate: bool = False) -> dict:
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
    from threadpoolctl import threadpool_limits

    from bttsim_stream.process import ProcessOptions, StreamingProcessor, process_arrays
    from bttsim_stream.paper.validate_processing import simulate

    run = simulate({"toa": {"method": method}} if method != "HP" else None)
    n_toa = int(run.toa_s.size)
    out: dict = {"method": method, "revolutions": int(run.opr_s.size), "toas": n_toa,
                 "simulation_wall_s": round(run.wall_s, 2)}
    with threadpool_limits(1):
        for name, opts in (("offline_default", ProcessOptions()), ("offline_no_prep", ProcessOptions(prep=False))):
            cpu, res = _best(lambda opts=opts: process_arrays(run.opr_s, run.toa_s, run.info, opts, truth=run.truth),
                              repeat)
            out[name] = {"cpu_s": round(cpu, 4), "toas_per_s": round(n_toa / cpu),
                         "mean_E_A_pct": round(res.summary["mean_E_A_pct"], 4)}

        def stream(run=run):
            proc = StreamingProcessor(run.info)
            latency = 0
            t0 = time.process_time()
            n_out = 0
            for n in range(run.opr_s.size):
                for o in proc.push(n, run.opr_s[n], run.toa_s[n]):
                    latency = max(latency, n - o.revolution)
                    n_out += 1
                proc.nsv_ready()  # the live NSV scan per completed block, as the processor session does
            n_out += len(proc.flush())
            proc.nsv_ready()
            t_push = time.process_time() - t0
            summary = proc.finish(run.truth)
            return t_push, time.process_time() - t0, latency, n_out, summary

        best = None
        for _ in range(repeat):
            r = stream()
            best = r if best is None or r[0] < best[0] else best
        t_push, t_total, latency, n_out, summary = best
        out["streaming"] = {"push_cpu_s": round(t_push, 4), "toas_per_s": round(n_toa / t_push),
                            "us_per_revolution": round(1e6 * t_push / run.opr_s.size, 1),
                            "with_final_report_cpu_s": round(t_total, 4),
                            "toas_per_s_with_final_report": round(n_toa / t_total),
                            "latency_revolutions": latency, "outputs": n_out,
                            "mean_E_A_pct": round(summary["mean_E_A_pct"], 4)}
        stage = simulate(ENGINE_STAGE)
        best = None
        for _ in range(repeat):
            r = stream(stage)
            best = r if best is None or r[0] < best[0] else best
        t_push, n_rev = best[0], stage.opr_s.size
        us_rev = 1e6 * t_push / n_rev
        out["streaming_engine_stage"] = {
            "n_blades": 60, "n_probes": 16, "revolutions": int(n_rev), "toas": int(stage.toa_s.size),
            "push_cpu_s": round(t_push, 4), "toas_per_s": round(stage.toa_s.size / t_push),
            "us_per_revolution": round(us_rev, 1),
            # 10 stages x 250 revolutions per second (15,000 rpm), one processor per stage
            "engine_core_share": round(10 * 250 * us_rev * 1e-6, 3)}
        if with_validate:
            out["validate_processing"] = _validate_cpu(repeat)
    out["target_toas_per_s"] = {"offline_default": 1_000_000, "streaming": 2_400_000,
                                "streaming_engine_stage": 2_400_000}
    out["ok"] = all(out[k]["toas_per_s"] >= v for k, v in out["target_toas_per_s"].items())
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--method", default="HP", choices=("HP", "AD", "PAD"))
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--validate", action="store_true",
                        help="also time the processing of bttsim validate --processing (about 10 s a repeat)")
    args = parser.parse_args()
    print(json.dumps(main(args.method, args.repeat, args.validate), indent=2))
