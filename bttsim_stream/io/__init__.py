"""Bus and recording I/O: key expressions (:mod:`.keys`), the protobuf codec (:mod:`.codec`,
the only module that touches generated schema code) and MCAP recording (:mod:`.mcap_io`).

Transport (Zenoh sessions, publishers) lives elsewhere; these modules only turn arrays into
bytes and bytes into files and back.
"""
