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

from importlib.metadata import PackageNotFoundError as _PackageNotFoundError
from importlib.metadata import version as _dist_version

try:  # one source of the version: the installed package's metadata (pyproject.toml)
    __version__ = _dist_version("bttsim-stream")
except _PackageNotFoundError:  # a source tree on sys.path that was never installed
    __version__ = "0+unknown"
