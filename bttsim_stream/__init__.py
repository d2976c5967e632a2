"""bttsim-stream: a virtual blade tip timing (BTT) acquisition system.

Conventions used across the package (written down once):

* SI units everywhere: s, m, rad, rad/s, N, kg. Names carry a unit suffix where it helps
  (``toa_s``, ``amp_pkpk_m``, ``tip_radius_m``).
* Rotor frame: +z is axial (flow direction, trailing edge at larger z); rotation and all
  angles (probes, blades, OPR) are anticlockwise from +x, seen from +z.
* Local directions at a point: radial (outward), tangential (direction of rotation),
  axial (+z). Tip and force shapes are stored in that (radial, tangential, axial) order.
* Axis order of event arrays: (revolution, blade, probe).
"""


def __getattr__(name: str) -> str:
    """``__version__``, read on first use (PEP 562): importlib.metadata takes 40 ms to import,
    which a command that writes no version need not pay."""
    if name != "__version__":
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version

    try:  # one source of the version: the installed package's metadata (pyproject.toml)
        value = version("bttsim-stream")
    except PackageNotFoundError:  # a source tree on sys.path that was never installed
        value = "0+unknown"
    globals()["__version__"] = value
    return value
