"""Test helpers for downstream teams: a virtual BTT acquisition system in a few lines.

Example
-------
::

    from bttsim_stream.testing import virtual_acquisition

    def test_my_pipeline():
        with virtual_acquisition(revolutions=50) as daq:
            results = my_pipeline.run(connect=daq.endpoint)     # your subscriber
            assert results.n_blades == daq.metadata.n_blades

Or, as a pytest fixture, in your ``conftest.py``::

    from bttsim_stream.testing import virtual_acquisition_fixture as bttsim_daq  # noqa: F401

``virtual_acquisition`` starts a simulator node in its own process, listening on a free
loopback port with multicast scouting off, waits until its metadata queryable answers, and
stops the process by its PID on exit. The simulator waits for ``wait_for`` subscribing nodes
(liveliness tokens under ``bttsim/<rig>/alive/``); without them it starts at once, and a
subscriber that comes later gets only the recent history from the publishers' caches: pass
``wait_for=1`` and declare a token ``bttsim/<rig>/alive/<name>`` in your subscriber for a
lossless start (and, once it has received the run metadata, a token ``bttsim/<rig>/ready/<name>``;
without it the simulator starts 5 s later).
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from .bus import codec, keys
from .bus.session import free_port, make_config, opened
from .scenario import Scenario, dumps_toml, load_scenario, scenario_from_dict

__all__ = ["free_port", "VirtualAcquisition", "virtual_acquisition", "virtual_acquisition_fixture"]


@dataclass(frozen=True)
class VirtualAcquisition:
    """A running simulator node.

    Attributes
    ----------
    endpoint : str
        Zenoh endpoint to connect to (``tcp/127.0.0.1:PORT``).
    rig : str
    metadata : RunInfo
        The run's acquisition metadata (probe angles, blade count, tip radius, clock...).
    process : subprocess.Popen
    """

    endpoint: str
    rig: str
    metadata: object
    process: subprocess.Popen

    def client_config(self):
        """A zenoh.Config that connects to the simulator (peer, loopback, no scouting)."""
        return make_config(connect=[self.endpoint])


@contextlib.contextmanager
def virtual_acquisition(scenario: str | os.PathLike | dict | None = None, *, revolutions: int | None = 100,
                        rate: str = "max", wait_for: int = 0, truth: bool = True, port: int | None = None,
                        start_timeout_s: float = 30.0, linger_s: float = 30.0):
    """Run a simulator node for the duration of a ``with`` block.

    Parameters
    ----------
    scenario : path, dict or None
        A scenario TOML file, a scenario as a dict (written to a temporary TOML), or None for
        the default scenario.
    revolutions : int or None
        Stop after this many revolutions (None: the whole run).
    rate : str
        ``"max"``, ``"realtime"`` or a factor.
    wait_for : int
        Let the simulator wait for this many other nodes' liveliness tokens before publishing.
    linger_s : float
        The node keeps serving metadata and its cache this long after the run.
    """
    with tempfile.TemporaryDirectory(prefix="bttsim-daq-") as tmp:
        if isinstance(scenario, dict):
            scn = scenario_from_dict(scenario)
        elif scenario is None:
            scn = Scenario()
        else:
            scn = load_scenario(scenario)
        path = Path(tmp) / "scenario.toml"
        path.write_text(dumps_toml(scn))
        port = port or free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        cmd = [sys.executable, "-m", "bttsim_stream.nodes.sim_node", str(path), "-l", endpoint,
               "--rate", rate, "--wait-for", str(wait_for), "--linger", str(linger_s)]
        if revolutions is not None:
            cmd += ["--revolutions", str(revolutions)]
        if not truth:
            cmd.append("--no-truth")
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            meta = None
            deadline = time.monotonic() + start_timeout_s
            with opened(make_config(connect=[endpoint])) as session:
                while meta is None and time.monotonic() < deadline:
                    if proc.poll() is not None:
                        raise RuntimeError(f"simulator node exited: {proc.stderr.read().decode()[-500:]}")
                    for reply in session.get(keys.meta_key(scn.run.rig), timeout=0.5):
                        if reply.ok is not None:
                            meta = codec.decode_run_metadata(reply.ok.payload.to_bytes()).body
                    if meta is None:
                        time.sleep(0.05)
            if meta is None:
                raise TimeoutError("the simulator node did not answer its metadata queryable")
            yield VirtualAcquisition(endpoint=endpoint, rig=scn.run.rig, metadata=meta, process=proc)
        finally:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
            proc.stderr.close()


try:
    import pytest

    @pytest.fixture
    def virtual_acquisition_fixture():
        """pytest fixture: a :class:`VirtualAcquisition` running 100 revolutions of the default scenario."""
        with virtual_acquisition() as daq:
            yield daq
except ImportError:  # pragma: no cover - pytest is optional
    pass
