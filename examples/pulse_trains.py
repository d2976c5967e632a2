"""Write the unlabelled pulse trains a rig would give (one OPR file, one file per probe) from a recording.

Usage::

    bttsim simulate short.toml --out sim.mcap
    python examples/pulse_trains.py sim.mcap trains/ --drop 0.01 --extra 0.001
    bttsim ingest --opr trains/opr.csv --probe 5=trains/probe0.csv ... --blades 29 --tip-radius-m 0.19 --out rig.mcap

The labels (revolution, blade) are dropped and each probe's TOAs sorted; ``--drop`` removes
that fraction of the pulses at random, ``--extra`` adds that fraction of spurious pulses at
random times (seeded). The script prints the matching ``bttsim ingest`` command line.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from bttsim_stream.offline import load_run


def write_pulse_trains(mcap, out_dir, *, drop: float = 0.0, extra: float = 0.0, seed: int = 0) -> dict:
    """Write ``opr.csv`` and ``probe<j>.csv`` (times in s, a header line); return the counts
    injected and the probe angles (deg)."""
    run = load_run(mcap)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    np.savetxt(out / "opr.csv", run.opr_s, fmt="%.17g", header="opr_s", comments="")
    counts = {"dropped": 0, "extra": 0, "angles_deg": np.rad2deg(run.meta.probe_angles_rad).tolist(),
              "n_blades": run.meta.n_blades, "tip_radius_m": run.meta.tip_radius_m}
    for j in range(run.meta.n_probes):
        t = run.toa_s[:, :, j].ravel()
        t = t[np.isfinite(t)]
        gone = rng.random(t.size) < drop
        fake = rng.uniform(run.opr_s[0], t.max(), int(round(extra * t.size)))
        pulses = np.sort(np.concatenate([t[~gone], fake]))
        np.savetxt(out / f"probe{j}.csv", pulses, fmt="%.17g", header="toa_s", comments="")
        counts["dropped"] += int(gone.sum())
        counts["extra"] += int(fake.size)
    return counts


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("mcap")
    p.add_argument("out_dir")
    p.add_argument("--drop", type=float, default=0.0, help="fraction of pulses removed at random")
    p.add_argument("--extra", type=float, default=0.0, help="fraction of spurious pulses added at random")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args()
    c = write_pulse_trains(a.mcap, a.out_dir, drop=a.drop, extra=a.extra, seed=a.seed)
    probes = " ".join(f"--probe {deg:.10g}={Path(a.out_dir) / f'probe{j}.csv'}"
                      for j, deg in enumerate(c["angles_deg"]))
    print(f"dropped {c['dropped']}, added {c['extra']} pulses")
    print(f"bttsim ingest --opr {Path(a.out_dir) / 'opr.csv'} {probes} --blades {c['n_blades']} "
          f"--tip-radius-m {c['tip_radius_m']:.6g} --eo 8 --out rig.mcap")


if __name__ == "__main__":
    main()
