"""Ingest rate and peak memory of ``bttsim ingest`` on long synthetic pulse trains (JSON out).

29 blades x 4 probes at 10,000 rpm with a +-1 % speed wobble, 1 % of the pulses dropped and
0.1 % spurious ones added, written to CSV (or Parquet) in a temporary folder; each size is
ingested in a fresh process (``bttsim ingest``), which reports its CPU time and peak
resident set size (``getrusage``).

    python bench/bench_ingest.py [--toas 1e6,4e6,2e7] [--format csv|parquet]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

N_BLADES, PROBES_DEG, RPM = 29, (5.0, 15.15, 23.82, 220.0), 10_000.0


def _write_trains(folder: Path, n_toas: int, fmt: str, seed: int = 0) -> list[str]:
    """OPR and probe files holding about ``n_toas`` TOAs; returns the ingest arguments."""
    rng = np.random.default_rng(seed)
    n_rev = int(np.ceil(n_toas / (N_BLADES * len(PROBES_DEG))))
    period = 60.0 / RPM * (1.0 + 0.01 * np.sin(np.arange(n_rev + 1) * 2 * np.pi / 500.0))
    opr = np.r_[0.0, np.cumsum(period)][:n_rev + 1]
    if fmt == "parquet":
        import pyarrow as pa
        import pyarrow.parquet as pq

        pq.write_table(pa.table({"opr_s": opr}), folder / "opr.parquet")
    else:
        np.savetxt(folder / "opr.csv", opr, fmt="%.17g")
    args = ["--opr", str(folder / f"opr.{fmt}")]
    frac = np.arange(N_BLADES) / N_BLADES
    for j, deg in enumerate(PROBES_DEG):
        path = folder / f"p{j}.{fmt}"
        writer = None
        with open(path, "wb") as fh:
            for lo in range(0, n_rev, 20_000):  # in blocks: the generator's memory stays small too
                hi = min(n_rev, lo + 20_000)
                pos = np.mod(deg / 360.0 - frac, 1.0)[None, :]
                t = opr[lo:hi, None] + period[lo:hi, None] * pos + 2e-7 * rng.standard_normal((hi - lo, N_BLADES))
                t = t.ravel()[rng.random(t.size) >= 0.01]
                t = np.sort(np.r_[t, rng.uniform(opr[lo], opr[hi], int(rng.poisson(0.001 * t.size)))])
                if fmt == "parquet":
                    writer = writer or pq.ParquetWriter(fh, pa.schema([("toa_s", pa.float64())]))
                    writer.write_table(pa.table({"toa_s": t}))
                else:
                    np.savetxt(fh, t, fmt="%.17g")
            if writer is not None:
                writer.close()
        args += ["--probe", f"{deg!r}={path}"]
    return args


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--toas", default="1e6,4e6", help="comma-separated TOA counts (default 1e6,4e6)")
    p.add_argument("--format", choices=("csv", "parquet"), default="csv")
    opts = p.parse_args()
    rows = []
    for n in (int(float(x)) for x in opts.toas.split(",")):
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp)
            t0 = time.perf_counter()
            args = _write_trains(folder, n, opts.format)
            t_gen = time.perf_counter() - t0
            size = sum(f.stat().st_size for f in folder.glob(f"*.{opts.format}"))
            code = ("import resource, sys, time; from bttsim_stream.cli import main; t = time.perf_counter(); "
                    "rc = main(sys.argv[1:]); print('WALL', time.perf_counter() - t); "
                    "ru = resource.getrusage(resource.RUSAGE_SELF); print('RSS', ru.ru_maxrss); "
                    "print('CPU', ru.ru_utime + ru.ru_stime); sys.exit(rc)")
            res = subprocess.run([sys.executable, "-c", code, "ingest", *args, "--blades", str(N_BLADES),
                                  "--tip-radius-m", "0.19", "--eo", "8", "--out", str(folder / "run.mcap")],
                                 capture_output=True, text=True)
            if res.returncode:
                raise SystemExit(res.stderr)
            out = dict(line.split(" ", 1) for line in res.stdout.splitlines()
                       if line.startswith(("WALL", "RSS", "CPU")))
            wall, cpu, rss_kb = float(out["WALL"]), float(out["CPU"]), int(out["RSS"])
            toas = int(res.stdout.split(" TOAs (")[0].rsplit(" ", 1)[1])
            rows.append({"toas": toas, "file_mb": round(size / 1e6, 1), "generate_s": round(t_gen, 1),
                         "ingest_s": round(wall, 2), "cpu_s": round(cpu, 2), "toa_per_cpu_s": round(toas / cpu),
                         "toa_per_s": round(toas / wall),
                         "peak_rss_mb": round(rss_kb / 1024, 1),
                         "rss_bytes_per_toa": round(rss_kb * 1024 / toas, 1),
                         "mcap_mb": round((folder / "run.mcap").stat().st_size / 1e6, 1)})
            print(json.dumps(rows[-1]), file=sys.stderr)
    print(json.dumps({"bench": "ingest", "format": opts.format, "blades": N_BLADES, "probes": len(PROBES_DEG),
                      "rpm": RPM,
                      "runs": rows}, indent=2))


if __name__ == "__main__":
    main()
