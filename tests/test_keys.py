"""Key expressions of the bus: construction, validation, parsing and matching."""

import numpy as np
import pytest

from bttsim_stream.errors import BttsimError
from bttsim_stream.bus import keys


def test_key_table():
    assert keys.opr_key("rig1") == "bttsim/rig1/opr"
    assert keys.toa_key("rig1", 3) == "bttsim/rig1/toa/3"
    assert keys.toa_key("rig1", np.int64(4)) == "bttsim/rig1/toa/4"
    assert keys.truth_key("r-2") == "bttsim/r-2/truth"
    assert keys.meta_key("rig1") == "bttsim/rig1/meta"
    assert keys.fits_key("rig1") == "bttsim/rig1/fit"
    assert keys.tw_key("rig1", 0) == "bttsim/rig1/tw/0"
    assert keys.resonance_key("rig1") == "bttsim/rig1/resonance"
    assert keys.alive_key("rig1", "sim") == "bttsim/rig1/alive/sim"
    assert keys.all_key() == "bttsim/*/**"
    assert keys.all_key("rig_A") == "bttsim/rig_A/**"
    assert keys.acquisition_keys("rig1") == ("bttsim/rig1/opr", "bttsim/rig1/toa/*")


@pytest.mark.parametrize("rig", ["", "a/b", "*", "rig 1", "rïg", None], ids=repr)
def test_bad_rig_names_are_refused(rig):
    with pytest.raises(BttsimError, match="invalid rig name"):
        keys.opr_key(rig)


@pytest.mark.parametrize("probe", [-1, 1.5, True, "2"], ids=repr)
def test_bad_probe_indices_are_refused(probe):
    with pytest.raises(BttsimError, match="probe index"):
        keys.toa_key("rig1", probe)


@pytest.mark.parametrize("key, expected", [
    ("bttsim/rig1/opr", "bttsim.v1.Opr"),
    ("bttsim/rig1/toa/0", "bttsim.v1.ToaBatch"),
    ("bttsim/rig1/truth", "bttsim.v1.TruthBatch"),
    ("bttsim/rig1/meta", "bttsim.v1.RunMetadata"),
    ("bttsim/rig1/fit", "bttsim.v1.BladeFits"),
    ("bttsim/rig1/tw/12", "bttsim.v1.TravellingWave"),
    ("bttsim/rig1/resonance", "bttsim.v1.ResonanceReport"),
])
def test_message_type_for_key(key, expected):
    assert keys.message_type_for_key(key) == expected


@pytest.mark.parametrize("key", ["bttsim/rig1/toa", "bttsim/rig1/toa/x", "bttsim/rig1/toa/01",
                                 "bttsim/rig1/opr/0", "other/rig1/opr", "bttsim/rig1/nope",
                                 "bttsim/*/opr", "bttsim/rig1/alive/sim"])
def test_message_type_for_bad_keys(key):
    with pytest.raises(BttsimError):
        keys.message_type_for_key(key)


def test_parse_key():
    info = keys.parse_key("bttsim/rig1/tw/3")
    assert (info.rig, info.kind, info.probe, info.node) == ("rig1", "tw", 3, None)
    info = keys.parse_key("bttsim/rig1/alive/proc-1")
    assert (info.kind, info.node, info.message_type) == ("alive", "proc-1", None)


@pytest.mark.parametrize("expr, key, ok", [
    ("bttsim/rig1/**", "bttsim/rig1/toa/3", True),
    ("bttsim/*/**", "bttsim/rig1/opr", True),
    ("bttsim/rig1/toa/*", "bttsim/rig1/toa/3", True),
    ("bttsim/rig1/toa/*", "bttsim/rig1/truth", False),
    ("bttsim/rig1/opr", "bttsim/rig1/opr", True),
    ("bttsim/rig2/**", "bttsim/rig1/opr", False),
    ("bttsim/**/opr", "bttsim/rig1/opr", True),
])
def test_key_matches(expr, key, ok):
    assert keys.key_matches(expr, key) is ok


def test_blind_processor_keys_never_match_truth():
    assert not any(keys.key_matches(e, keys.truth_key("rig1")) for e in keys.acquisition_keys("rig1"))
