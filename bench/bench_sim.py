"""Benchmark: run-up simulation speed and memory, core and ``bttsim simulate`` (prints JSON).

Usage::

    python bench/bench_sim.py               # every case, best of 3 (about 3 minutes)
    python bench/bench_sim.py --repeat 1    # one run per case
    python bench/bench_sim.py --quick       # one run per case, no 1000 s memory run

Cases (paper Table 1 run-up, 1000 -> 4000 rpm in 130 s, HP, unless said): the default
scenario; 2 % random stiffness mistuning (every one of the 145 modes responds); 1 probe;
16 probes; 100 blades. For each case, in fresh processes, on one core
(``OMP_NUM_THREADS=1``), CPU time (user + system, not wall time: the machine is shared):

* ``core``: :class:`~bttsim_stream.sim.core.RunUpSimulator` over the whole run (the model
  is built first and not counted): CPU seconds, real-time factor (simulated seconds per CPU
  second), us per TOA, CPU seconds of envelope integration per simulated second, CPU us per
  TOA of the crossings, peak RSS of the process;
* ``simulate``: ``bttsim simulate SCENARIO --out FILE.mcap`` end to end (interpreter start,
  imports, model build, simulation, encoding, MCAP): CPU seconds, real-time factor, peak RSS;
  with the package's bytecode cached, as installed packages have it (see ``_env``).

CPU times are the best of ``--repeat`` runs. ``memory`` compares the core's peak RSS over
1000 s with that over 130 s (the same ramp, stretched): it should stay flat.

``centrifugal``: the default scenario with ``[model] centrifugal = true`` (the built-in FE
model's modes at 17 speeds, centrifugal stiffening and spin softening: the
:mod:`~bttsim_stream.sim.speed_modal` path; the model build, about 1 s, is not part of the
core's time but is of ``simulate``'s); target (issue 13) core >= 20x real time.

Targets (issue 17): default core >= 100x real time, ``bttsim simulate`` >= 50x, mistuned
core >= 40x, peak RSS of the 1000 s run within 10 % of the 130 s run's. Issue 14: with the
default ``[acquisition.signal]`` chain on, the core >= 5x real time; with its raw signals
published, ``raw_signal`` gives the ``signal/<probe>`` payload bytes on the bus per minute of
run (whole run and the busiest 32-revolution chunk) and the MCAP file per minute (zstd
chunks), target < 200 MB per minute.

``--case NAME`` (repeatable) runs only the named cases.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time

SIXTEEN_PROBES = [5.0, 10.6, 15.15, 23.82, 40.0, 70.0, 100.0, 148.5, 190.35, 202.11, 220.0, 245.0, 255.6, 280.0,
                  301.5, 330.0]

CASES = [
    ("default", {}),
    ("mistuned 2 %", {"model": {"stiffness_std": 0.02}}),
    ("1 probe", {"probes": {"angles_deg": [5.0]}}),
    ("16 probes", {"probes": {"angles_deg": SIXTEEN_PROBES}}),
    ("100 blades", {"rotor": {"n_blades": 100}}),
    ("signal chain", {"acquisition": {"clock_hz": 1e8, "signal": {"enabled": True}}}),
    ("signal chain, raw signals published", {"acquisition": {"clock_hz": 1e8, "signal": {"enabled": True,
                                                                                          "publish": True}}}),
    ("centrifugal", {"model": {"centrifugal": True}}),
]
#: The case whose raw-signal volume is measured.
RAW = "signal chain, raw signals published"
LONG = {"speed": {"start_rpm": 1000.0, "end_rpm": 4000.0, "duration_s": 1000.0}}

TARGETS = {"default_core_rtf": 100, "default_simulate_rtf": 50, "mistuned_core_rtf": 40,
           "rss_1000s_over_130s_max": 1.10, "signal_core_rtf": 5, "raw_signal_mb_per_min_max": 200,
           "centrifugal_core_rtf": 20}


def _env() -> dict:
    """One BLAS thread; and bytecode written and read as in any installed Python package
    (``PYTHONDONTWRITEBYTECODE`` dropped: with it set, as on some shared machines, every
    ``bttsim simulate`` compiled the package's ~60 modules from source, ~0.17 s CPU; the first
    of ``--repeat`` runs writes the ``__pycache__`` the others read)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def _core(overrides: dict) -> dict:
    """One core run in this process (called with ``--core``)."""
    from bttsim_stream.scenario import scenario_from_dict
    from bttsim_stream.sim.core import RunUpSimulator

    from bttsim_stream.model import build_model

    scn = scenario_from_dict(overrides)
    t0 = time.process_time()
    model = build_model(scn)
    build_s = time.process_time() - t0
    t0 = time.process_time()
    sim = RunUpSimulator(scn, model)
    n_toa = 0
    for batch in sim:
        n_toa += batch.toa_s.size
    cpu = time.process_time() - t0
    dur = scn.speed.duration_s
    return {
        "duration_s": dur, "n_blades": model.n_blades, "n_probes": len(scn.probes.angles_deg),
        "n_modes": model.n_modes, "n_active_modes": int(sim.integrator.active.size), "n_toas": n_toa,
        "model_build_cpu_s": round(build_s, 3), "cpu_s": round(cpu, 3),
        "real_time_factor": round(dur / cpu, 1), "us_per_toa": round(1e6 * cpu / max(n_toa, 1), 3),
        "envelope_s_per_sim_s": round(sim.timing["envelopes_s"] / dur, 5),
        "crossing_us_per_toa": round(1e6 * sim.timing["crossings_s"] / max(n_toa, 1), 3),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
    }


def _raw_volume(overrides: dict) -> dict:
    """Payload bytes of the raw-signal keys over the whole run (called with ``--raw``)."""
    from bttsim_stream.acquisition import AcquisitionStream
    from bttsim_stream.scenario import scenario_from_dict

    scn = scenario_from_dict(overrides)
    stream = AcquisitionStream(scn, chunk_revolutions=32)
    total = signal = 0
    peak = 0.0
    for batch, msgs in stream.batches():
        sizes = [(len(m.payload), "/signal/" in m.key) for m in msgs]
        chunk = sum(n for n, is_signal in sizes if is_signal)
        total += sum(n for n, _ in sizes)
        signal += chunk
        span = float(batch.opr_s[-1] - batch.opr_s[0]) * len(batch.opr_s) / max(len(batch.opr_s) - 1, 1)
        peak = max(peak, chunk / span * 60.0 / 1e6)
    minutes = scn.speed.duration_s / 60.0
    return {"signal_payload_mb": round(signal / 1e6, 1), "all_payload_mb": round(total / 1e6, 1),
            "bus_mb_per_min": round(signal / 1e6 / minutes, 1), "peak_bus_mb_per_min": round(peak, 1)}


def _child(cmd: list) -> tuple[float, float, str]:
    """Run ``cmd``; its CPU seconds (user + system), peak RSS (MB) and stdout."""
    with tempfile.TemporaryFile("w+") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.PIPE, text=True, env=_env())
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        err = proc.stderr.read()
        proc.stderr.close()
        if proc.returncode:
            raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}): {err}")
        out.seek(0)
        return usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024, out.read()


def _best_core(overrides: dict, repeat: int) -> dict:
    runs = []
    for _ in range(repeat):
        _, _, text = _child([sys.executable, __file__, "--core", json.dumps(overrides)])
        runs.append(json.loads(text.strip().splitlines()[-1]))
    best = min(runs, key=lambda r: r["cpu_s"])
    best["envelope_s_per_sim_s"] = min(r["envelope_s_per_sim_s"] for r in runs)
    best["crossing_us_per_toa"] = min(r["crossing_us_per_toa"] for r in runs)
    best["peak_rss_mb"] = max(r["peak_rss_mb"] for r in runs)
    return best


def _best_simulate(overrides: dict, duration_s: float, repeat: int) -> dict:
    from bttsim_stream.scenario import dumps_toml, scenario_from_dict

    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "scenario.toml")
        with open(path, "w") as f:
            f.write(dumps_toml(scenario_from_dict(overrides)))
        out = os.path.join(tmp, "run.mcap")
        cpu, rss = [], []
        for _ in range(repeat):
            c, r, text = _child([sys.executable, "-m", "bttsim_stream.cli", "simulate", path, "--out", out, "--quiet"])
            cpu.append(c)
            rss.append(r)
        size = os.path.getsize(out)
    best = min(cpu)
    return {"cpu_s": round(best, 3), "real_time_factor": round(duration_s / best, 1), "peak_rss_mb": round(max(rss), 1),
            "mcap_mb": round(size / 1e6, 1), "summary": text.strip().splitlines()[-1]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="runs per measurement (best CPU time)")
    parser.add_argument("--quick", action="store_true", help="one run per case, no 1000 s memory run")
    parser.add_argument("--case", action="append", help="run only this case (repeatable)")
    parser.add_argument("--core", help=argparse.SUPPRESS)
    parser.add_argument("--raw", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.core is not None:
        os.environ.update(_env())
        print(json.dumps(_core(json.loads(args.core))))
        return
    if args.raw is not None:
        os.environ.update(_env())
        print(json.dumps(_raw_volume(json.loads(args.raw))))
        return
    repeat = 1 if args.quick else max(1, args.repeat)
    rows = []
    for name, overrides in CASES:
        if args.case and name not in args.case:
            continue
        core = _best_core(overrides, repeat)
        row = {"case": name, "scenario": overrides, "core": core,
               "simulate": _best_simulate(overrides, core["duration_s"], repeat)}
        rows.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
    raw = None
    by = {r["case"]: r for r in rows}
    if RAW in by:
        _, _, text = _child([sys.executable, __file__, "--raw", json.dumps(dict(CASES)[RAW])])
        raw = json.loads(text.strip().splitlines()[-1])
        raw["mcap_mb_per_min"] = round(by[RAW]["simulate"]["mcap_mb"] / (by[RAW]["core"]["duration_s"] / 60.0), 1)
    memory = None
    if not args.quick and "default" in by:
        long = _best_core(LONG, 1)
        rss_130 = rows[0]["core"]["peak_rss_mb"]
        memory = {"rss_130s_mb": rss_130, "rss_1000s_mb": long["peak_rss_mb"],
                  "ratio": round(long["peak_rss_mb"] / rss_130, 3), "core_1000s": long}

    def rtf(case, part):
        return by[case][part]["real_time_factor"] if case in by else None

    def at_least(value, target):
        return None if value is None else value >= target

    result = {
        "benchmark": "simulation", "cpu_seconds": "user + system CPU time, best of repeat", "repeat": repeat,
        "machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine(),
                    "load_average": [round(x, 2) for x in os.getloadavg()]},
        "targets": TARGETS,
        "met": {
            "default_core_rtf": at_least(rtf("default", "core"), TARGETS["default_core_rtf"]),
            "default_simulate_rtf": at_least(rtf("default", "simulate"), TARGETS["default_simulate_rtf"]),
            "mistuned_core_rtf": at_least(rtf("mistuned 2 %", "core"), TARGETS["mistuned_core_rtf"]),
            "rss_flat": None if memory is None else memory["ratio"] <= TARGETS["rss_1000s_over_130s_max"],
            "signal_core_rtf": at_least(rtf("signal chain", "core"), TARGETS["signal_core_rtf"]),
            "centrifugal_core_rtf": at_least(rtf("centrifugal", "core"), TARGETS["centrifugal_core_rtf"]),
            "raw_signal_mb_per_min": None if raw is None else (
                max(raw["peak_bus_mb_per_min"], raw["mcap_mb_per_min"]) < TARGETS["raw_signal_mb_per_min_max"]),
        },
        "runs": rows, "memory": memory, "raw_signal": raw,
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
