"""Shared pytest configuration: the test tiers (declared in ``pyproject.toml``).

* ``unit`` -- in-process (at most a short Python subprocess), no network: the default of every
  test that declares no tier;
* ``slow`` -- in-process but heavy: the bounded fuzz and the tight ``solve_ivp`` references;
* ``integration`` -- real node processes, Zenoh sessions on loopback, ``bttsim run``;
* ``browser`` -- the Rerun web viewer in headless Chromium (slow: software rendering).

``python -m pytest`` runs them all; ``-m unit``, ``-m "unit or slow"`` or ``-m "not browser"`` select.
"""

import os
import shutil
import tempfile

import pytest

from bttsim_stream.threads import single_threaded_blas

# The Python processes the tests start (commands, nodes, `bttsim run`: about a thousand) share
# one bytecode cache for the session, outside the source tree, even where the shell says
# PYTHONDONTWRITEBYTECODE: each would otherwise compile the package's modules again (0.1 s
# of every start). A cache the shell already names is used as it is.
_PYCACHE = None
if "PYTHONPYCACHEPREFIX" not in os.environ:
    _PYCACHE = os.environ["PYTHONPYCACHEPREFIX"] = tempfile.mkdtemp(prefix="bttsim-tests-pycache-")
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)

# one BLAS thread, as in every bttsim process: the in-process references sum in the same order
# as the nodes and commands they are compared with, whatever OMP_NUM_THREADS the shell has
single_threaded_blas()

TIERS = ("unit", "slow", "integration", "browser")


def pytest_collection_modifyitems(config, items):
    for item in items:
        if not any(item.get_closest_marker(t) for t in TIERS):
            item.add_marker(pytest.mark.unit)


def pytest_sessionfinish(session, exitstatus):
    if _PYCACHE is not None:
        shutil.rmtree(_PYCACHE, ignore_errors=True)
