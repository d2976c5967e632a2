"""The bus: everything between the numerics and the wire (or the file).

* :mod:`.keys` -- key expressions ``bttsim/<rig>/...`` and the message type on each;
* :mod:`.codec` -- protobuf <-> the library's dataclasses (the only user of generated code);
* :mod:`.stream` -- the message record, sequence numbers, revolution assembly, results to
  messages;
* :mod:`.recording` -- MCAP files: write raw payloads, read them back (also from a cut file);
* :mod:`.session` -- Zenoh sessions: flags, configuration, attachments, liveliness, stopping.

The numerical packages (``model``, ``sim``, ``process``) never import this one.
"""
