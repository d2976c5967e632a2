"""Runnable node programs (installed as ``bttsim_stream.nodes``)."""
