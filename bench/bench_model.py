"""Benchmark: build time of the default bladed-disk model (prints JSON).

Usage: ``python bench/bench_model.py [--repeat N]``. Target: <= 5 s on this machine.

Also the speed-dependent model (``[model] centrifugal = true``, 17 speeds to 4800 rpm): its
build time, the family-1 stiffening, and how well the file's interpolation contract (a natural
cubic spline in Omega^2 of omega^2 and of the shape components) reproduces the modes between
its speeds: a 33-speed build's odd speeds (the midpoints of the 17-speed grid) against the
spline through its even ones.
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
    _mis = build_model(stiffness_factors=1 + 0.02 * np.random.default_rng(0).standard_normal(29),
                       mass_factors=np.ones(29))
    mistuned_s = time.perf_counter() - t

    d = BladedDiskDesign()
    modes = expand_cyclic(d, solve_cyclic(d))
    K, M, _ = assemble_full_wheel(d)
    Phi = modes.shapes.reshape(len(modes.freq_hz), -1).T
    orth = float(np.abs(Phi.T @ (M @ Phi) - np.eye(Phi.shape[1])).max())
    fam1 = model.campbell_freq_hz[0]

    from scipy.interpolate import CubicSpline

    from bttsim_stream.scenario import Model, Scenario
    times_c = []
    for _ in range(max(1, args.repeat // 2)):
        t = time.perf_counter()
        cmodel = build_model(Scenario(model=Model(centrifugal=True)))
        times_c.append(time.perf_counter() - t)
    e = cmodel.extra
    W = e["speed_rad_s"][-1]
    camp = e["campbell_freq_hz_at_speed"]
    southwell = (camp[-1, 0] ** 2 - camp[0, 0] ** 2) / (W / (2 * np.pi)) ** 2
    dense = build_model(Scenario(model=Model(centrifugal=True, centrifugal_speeds=33)))
    x = dense.extra["speed_rad_s"] ** 2
    f2 = dense.extra["freq_hz_at_speed"] ** 2
    spl = CubicSpline(x[::2], f2[::2], bc_type="natural", axis=0)
    f_err = np.abs(np.sqrt(spl(x[1::2])) - np.sqrt(f2[1::2]))
    tip = dense.extra["tip_shapes_at_speed"].reshape(x.size, dense.n_modes, -1)
    spl = CubicSpline(x[::2], tip[::2], bc_type="natural", axis=0)
    t_err = np.abs(spl(x[1::2]) - tip[1::2]).max(axis=(0, 2)) / np.abs(tip).max(axis=(0, 2))
    fam = dense.family
    centrifugal = {
        "build_s_min": round(min(times_c), 3),
        "n_speeds": int(e["speed_rad_s"].size),
        "max_rpm": round(float(W * 30 / np.pi), 1),
        "tracking_min_mac": cmodel.meta["provenance"]["centrifugal"]["tracking_min_mac"],
        "family1_nd0_14_hz_at_max": [round(float(f), 3) for f in camp[-1, 0]],
        "family1_southwell_nd0_nd1_nd14": [round(float(southwell[i]), 4) for i in (0, 1, 14)],
        "file_mb": round(sum(v.nbytes for v in cmodel.as_arrays().values()) / 1e6, 1),
        "spline_freq_err_hz_max": float(f_err.max()),
        "spline_freq_err_hz_family1_max": float(f_err[:, fam == 0].max()),
        "spline_tip_shape_rel_err_family1_max": float(t_err[fam == 0].max()),
        "spline_tip_shape_rel_err_max": float(t_err.max()),
    }
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
        "centrifugal": centrifugal,
    }, indent=2))


if __name__ == "__main__":
    main()
