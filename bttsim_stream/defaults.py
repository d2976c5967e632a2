"""User-visible defaults that several layers share, in one place (no dependencies).

All servers bind to loopback (127.0.0.1) by default; the web viewer's ``--bind`` chooses another
address on purpose.
"""

__all__ = ["DEFAULT_WEB_PORT", "DEFAULT_GRPC_PORT", "DEFAULT_BIND", "DEFAULT_RIG", "MAX_BLADES", "MAX_PROBES",
           "MAX_ENGINE_ORDER", "MAX_RPM", "MAX_REVOLUTIONS", "MAX_TIP_AMPLITUDE_FRACTION"]

#: HTTP port of the Rerun web viewer (``--web``).
DEFAULT_WEB_PORT = 9090
#: Port of the Rerun gRPC data server that the web viewer connects to.
DEFAULT_GRPC_PORT = 9876
#: Address the web viewer's two servers (page and data) listen on (``--bind``).
DEFAULT_BIND = "127.0.0.1"
#: Rig name of the default scenario (keys ``bttsim/<rig>/...``).
DEFAULT_RIG = "rig1"

# -- limits: checked where input enters (scenario, model file, recording, bus) -------------
#: Most blades of the built-in model (its memory grows as ``n_families * n_blades**2``:
#: about 0.6 GB at 200 blades and 5 families, 2.2 GB with 20 families) and of a run.
MAX_BLADES = 200
#: Most probes of a run.
MAX_PROBES = 64
#: Most speeds of a speed-dependent (centrifugal) modal model and of the run metadata's
#: Campbell families.
MAX_SPEEDS = 64
#: Highest engine order.
MAX_ENGINE_ORDER = 1000
#: Fastest rotor speed of a scenario, rpm.
MAX_RPM = 1.0e6
#: Highest natural frequency a model file may hold, Hz (blade modes are below tens of kHz).
MAX_MODE_FREQ_HZ = 1.0e6
#: Most revolutions of one run (about 4 h at 4000 rpm; the default run has 5,400).
MAX_REVOLUTIONS = 1_000_000
#: Largest tip amplitude as a fraction of the tip radius: zero to peak, the upper bound of any
#: tip node's displacement over the run (``bttsim_stream.sim.bounds.tip_amplitude_bound``). The
#: modal model is linear (small displacements); beyond this a scenario is refused before
#: anything is simulated.
MAX_TIP_AMPLITUDE_FRACTION = 0.05
