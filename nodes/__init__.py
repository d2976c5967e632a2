"""Runnable node programs (installed as ``bttsim_stream.nodes``).

Each module is a thin program on the shared node runtime (:mod:`bttsim_stream.runtime`)
and declares one :class:`~bttsim_stream.runtime.NodeProgram` (``PROGRAM``): its name, help,
arguments and ``main``. Run one as ``bttsim node NAME ...``, ``python -m
bttsim_stream.nodes NAME ...``, ``python -m bttsim_stream.nodes.<module> ...`` or its console
script (``bttsim-sim-node``, ``bttsim-recorder``, ``bttsim-processor``, ``bttsim-viewer``,
``bttsim-replay``): the same flags and help everywhere. Every ``bttsim`` command imports every
node module to build its parsers, so a module imports at its top only what its parser needs
(the runtime, the keys); its ``main`` imports the node's machinery (the simulator, the codec,
MCAP, the processing, the views).

=============  ====================  ===============================================
name           module                what it does
=============  ====================  ===============================================
``sim``        ``sim_node``          publishes a scenario's run-up (OPR, TOAs, truth)
``recorder``   ``recorder_node``     records every key of a rig to MCAP
``processor``  ``processor_node``    fits, travelling waves, resonance report (blind)
``viewer``     ``viewer_node``       Rerun views of the bus
``replay``     ``replay_node``       republishes a recording
``router``     ``router_node``       a Zenoh router for multi-host layouts
=============  ====================  ===============================================
"""

import importlib

#: Node name -> module (in this package).
MODULES = {"sim": "sim_node", "recorder": "recorder_node", "processor": "processor_node",
           "viewer": "viewer_node", "replay": "replay_node", "router": "router_node"}


def program(name: str):
    """The :class:`~bttsim_stream.runtime.NodeProgram` of node ``name``."""
    return importlib.import_module(f"{__name__}.{MODULES[name]}").PROGRAM


def programs() -> list:
    """Every node program, in the order of :data:`MODULES`."""
    return [program(n) for n in MODULES]
