"""Benchmark: build time of the default bladed-disk model (prints JSON).

Usage: ``python bench/bench_model.py [--repeat N]``. Target: <= 5 s on this machine.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    t0 = time.perf_counter()
    from bttsim_stream.model import build_model
    from bttsim_stream.model.bladed_disk import BladedDiskDesign, assemble_full_wheel, expand_cyclic, solve_cyclic
    import_s = time.perf_counter() - t0

    times = []
    for _ in range(args.repeat):
        t = time.perf_counter()
        model = build_model()
        times.append(time.perf_counter() - t)
    t = time.perf_counter()
    mis = build_model(stiffness_factors=1 + 0.02 * np.random.default_rng(0).standard_normal(29),
                      mass_factors=np.ones(29))
    mistuned_s = time.perf_counter() - t

    d = BladedDiskDesign()
    modes = expand_cyclic(d, solve_cyclic(d))
    K, M, _ = assemble_full_wheel(d)
    Phi = modes.shapes.reshape(len(modes.freq_hz), -1).T
    orth = float(np.abs(Phi.T @ (M @ Phi) - np.eye(Phi.shape[1])).max())
    fam1 = model.campbell_freq_hz[0]
    print(json.dumps({
        "benchmark": "model_build",
        "import_s": round(import_s, 3),
        "build_tuned_s_min": round(min(times), 4),
        "build_tuned_s_median": round(float(np.median(times)), 4),
        "build_mistuned_full_wheel_s": round(mistuned_s, 3),
        "n_modes": model.n_modes,
        "full_wheel_dof": int(K.shape[0]),
        "orthogonality_error": orth,
        "blade_alone_hz": [round(float(f), 3) for f in model.blade_alone_freq_hz],
        "family1_nd0_14_hz": [round(float(f), 3) for f in fam1],
        "target_s": 5.0,
    }, indent=2))


if __name__ == "__main__":
    main()
