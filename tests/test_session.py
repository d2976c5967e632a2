"""Zenoh session configuration: loopback defaults, and a -c file merged with them."""

import json

import pytest

from bttsim_stream.bus.session import make_config
from bttsim_stream.errors import BttsimError


def _get(conf, key):
    return json.loads(conf.get_json(key))


def test_defaults_listen_only_where_asked_and_do_not_scout():
    conf = make_config(connect=["tcp/127.0.0.1:7447"])
    assert _get(conf, "listen/endpoints") == [] and _get(conf, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert _get(conf, "scouting/multicast/enabled") is False and _get(conf, "mode") == "peer"


def test_a_config_file_is_merged_with_the_loopback_defaults(tmp_path):
    bare = tmp_path / "bare.json5"
    bare.write_text('{ transport: { unicast: { max_sessions: 100 } } }')
    conf = make_config(config_file=str(bare), listen=["tcp/127.0.0.1:7001"])
    # zenoh's own default would listen on every interface and scout by multicast
    assert _get(conf, "listen/endpoints") == ["tcp/127.0.0.1:7001"]
    assert _get(conf, "scouting/multicast/enabled") is False and _get(conf, "mode") == "peer"
    assert _get(conf, "transport/unicast/max_sessions") == 100
    assert _get(make_config(config_file=str(bare)), "listen/endpoints") == []


def test_what_the_file_sets_wins_and_command_line_endpoints_are_added(tmp_path):
    full = tmp_path / "full.json5"
    full.write_text('{ mode: "client", listen: { endpoints: ["tcp/127.0.0.1:7002"] }, '
                    'scouting: { multicast: { enabled: true } } }')
    conf = make_config(config_file=str(full), connect=["tcp/127.0.0.1:7003"])
    assert _get(conf, "mode") == "client" and _get(conf, "scouting/multicast/enabled") is True
    assert _get(conf, "listen/endpoints") == ["tcp/127.0.0.1:7002"]
    assert _get(conf, "connect/endpoints") == ["tcp/127.0.0.1:7003"]
    assert _get(make_config(config_file=str(full), listen=["tcp/127.0.0.1:7004"]),
                "listen/endpoints") == ["tcp/127.0.0.1:7004"]  # bttsim run gives each node its own


@pytest.mark.parametrize("kwargs, match", [
    (dict(config_file="/nonexistent.json5"), "no such Zenoh configuration file"),
    (dict(connect=["localhost"]), "bad zenoh endpoint"),
    (dict(mode="client"), "client mode needs"),
], ids=["missing-file", "bad-endpoint", "client-without-endpoint"])
def test_bad_configuration_is_a_one_line_error(kwargs, match):
    with pytest.raises(BttsimError, match=match) as exc:
        make_config(**kwargs)
    assert "\n" not in str(exc.value)
