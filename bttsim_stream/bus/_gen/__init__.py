"""Generated protobuf code (``scripts/gen_proto.py``); do not edit. Imported only by
:mod:`bttsim_stream.io.codec`."""
