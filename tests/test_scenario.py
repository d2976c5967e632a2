"""Tests of the scenario file: defaults, round trip, validation messages, CLI."""

from __future__ import annotations

import dataclasses
import math
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from bttsim_stream.errors import BttsimError, ScenarioError
from bttsim_stream.fieldspec import comments
from bttsim_stream.scenario import (
    SECTIONS,
    Acquisition,
    Signal,
    Excitation,
    Model,
    Probes,
    Rotor,
    Run,
    Scenario,
    Speed,
    Toa,
    default_toml,
    dumps_toml,
    load_scenario,
    scenario_from_dict,
    scenario_to_dict,
)

REPO = Path(__file__).resolve().parents[1]


def _write(tmp_path: Path, text: str, name: str = "scenario.toml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def _assert_same(a: Scenario, b: Scenario) -> None:
    """Field-by-field equality with a readable failure, then whole-object equality."""
    for name in SECTIONS:
        va, vb = getattr(a, name), getattr(b, name)
        if name == "excitation":
            assert len(va) == len(vb)
            pairs = list(zip(va, vb))
        else:
            pairs = [(va, vb)]
        for sa, sb in pairs:
            for f in dataclasses.fields(sa):
                x, y = getattr(sa, f.name), getattr(sb, f.name)
                assert x == y, f"[{name}] {f.name}: {x!r} != {y!r}"
                assert type(x) is type(y), f"[{name}] {f.name}: {type(x)} vs {type(y)}"
    assert a == b


# ----------------------------------------------------------------------------- defaults


def test_default_is_table_1():
    s = Scenario()
    assert (s.speed.start_rpm, s.speed.end_rpm, s.speed.duration_s) == (1000.0, 4000.0, 130.0)
    assert s.speed.segments == ()
    assert s.model.damping_beta_s == 9e-6
    assert s.model.source == "builtin"
    assert s.model.n_families == 5
    assert len(s.excitation) == 1
    e = s.excitation[0]
    assert (e.engine_order, e.nodal_diameter, e.amplitude_n) == (8, 1, 2.25)
    assert e.direction == (0.0, 0.0, 1.0) and e.node == "leading_edge"
    assert s.probes.angles_deg == (5.0, 15.15, 23.82, 220.0, 301.5)
    assert s.probes.axial_position_m == 0.01226
    assert s.rotor.n_blades == 29
    assert s.rotor.nominal_node == 5
    assert s.rotor.nominal_offset_from_te_m == pytest.approx(1.75e-3)
    assert s.rotor.tip_axial_extent_m == pytest.approx(0.0202523 * math.sin(math.radians(41.5)))
    assert 0 <= s.probes.axial_position_m <= s.rotor.tip_axial_extent_m
    assert s.toa.method == "HP" and s.toa.axial_interpolation is True
    assert all(getattr(s.acquisition, f.name) == 0.0 for f in dataclasses.fields(Acquisition) if f.name != "signal")
    assert s.acquisition.signal.enabled is False
    assert (s.run.rig, s.run.seed) == ("rig1", 0)


def test_default_toml_parses_back_to_default(tmp_path):
    text = default_toml()
    _assert_same(scenario_from_dict(tomllib.loads(text)), Scenario())
    _assert_same(load_scenario(_write(tmp_path, text)), Scenario())


def test_empty_file_is_default(tmp_path):
    _assert_same(load_scenario(_write(tmp_path, "")), Scenario())


def test_every_field_documented():
    text = default_toml()
    lines = text.splitlines()
    for _name, cls in [*SECTIONS.items(), ("acquisition.signal", Signal)]:
        for f in dataclasses.fields(cls):
            assert f.name in cls.__doc__, f"{cls.__name__}.{f.name} missing from docstring"
            assert comments(cls)[f.name], f"{cls.__name__}.{f.name} has no TOML comment"
            if f.name in ("segments", "signal"):  # written as an example / as its own table
                continue
            i = next(i for i, line in enumerate(lines) if line.startswith(f"{f.name} = "))
            assert lines[i - 1].startswith("#"), f"{f.name} has no comment above it"


def test_sections_are_frozen():
    s = Scenario()
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.rotor.n_blades = 3  # type: ignore[misc]


# ----------------------------------------------------------------------------- round trip


def _custom(tmp_path: Path) -> Scenario:
    n = 12
    return Scenario(
        run=Run(rig="test-rig_2", seed=123456789),
        rotor=Rotor(n_blades=n, tip_radius_m=0.2537, stagger_deg=33.3, tip_chord_m=0.031,
                    n_tip_nodes=7, tip_node_spacing_m=0.001, nominal_node=3),
        model=Model(source=str(tmp_path / 'my "model" \\ é.npz'), damping_beta_s=1.234567e-5,
                    n_families=3, disk_asymmetry=True,
                    stiffness_factors=tuple(1.0 + 0.01 * i for i in range(n)),
                    mass_factors=np.linspace(0.99, 1.01, n), stiffness_std=0.0, mass_std=0.0),
        speed=Speed(start_rpm=1500, segments=((30.0, 2500.0), (20.0, 2500.0),
                                              {"duration_s": 0.1, "end_rpm": 3999.9})),
        excitation=[
            Excitation(engine_order=3, nodal_diameter=0, amplitude_n=0.1 + 0.2,
                       direction=[1, -2.5, 1e-300], node="trailing_edge"),
            Excitation(engine_order=11, nodal_diameter=11, amplitude_n=7),
        ],
        probes=Probes(angles_deg=(0.0, 359.999999999, 1 / 3), axial_position_m=0.0,
                      opr_angle_deg=270.5),
        toa=Toa(method="PAD", grid_step_s=1e-7, axial_interpolation=False),
        acquisition=Acquisition(clock_hz=100e6, trigger_jitter_s=1e-7,
                                probe_angle_error_deg=0.05, opr_jitter_s=2e-8,
                                speed_fluctuation_rpm=0.3),
    )


def test_round_trip_non_default(tmp_path):
    s = _custom(tmp_path)
    text = dumps_toml(s)
    _assert_same(load_scenario(_write(tmp_path, text)), s)
    _assert_same(load_scenario(_write(tmp_path, dumps_toml(s, comments=True))), s)
    _assert_same(scenario_from_dict(scenario_to_dict(s)), s)
    assert text.count("[[excitation]]") == 2
    assert "end_rpm = " not in text.split("[speed]")[1].split("[")[0]


def test_round_trip_plain_ramp_and_mass_std(tmp_path):
    s = Scenario(speed=Speed(start_rpm=800.5, end_rpm=8000, duration_s=12.25),
                 model=Model(stiffness_std=0.03, mass_std=0.499))
    _assert_same(load_scenario(_write(tmp_path, dumps_toml(s))), s)


def test_normalised_types():
    s = _custom(Path("/tmp"))
    assert isinstance(s.excitation, tuple)
    assert s.excitation[0].direction == (1.0, -2.5, 1e-300)
    assert all(type(x) is float for x in s.model.mass_factors)
    assert type(s.speed.start_rpm) is float and type(s.excitation[1].amplitude_n) is float


def test_speed_segments_profile():
    sp = Speed(start_rpm=1000.0, segments=((30.0, 2500.0), (20.0, 2500.0), (60.0, 4000.0)))
    assert sp.total_duration_s == sp.duration_s == 110.0
    assert sp.end_rpm == 4000.0
    t, rpm = sp.breakpoints()
    np.testing.assert_array_equal(t, [0.0, 30.0, 50.0, 110.0])
    np.testing.assert_array_equal(rpm, [1000.0, 2500.0, 2500.0, 4000.0])
    t, rpm = Speed().breakpoints()
    np.testing.assert_array_equal(t, [0.0, 130.0])
    np.testing.assert_array_equal(rpm, [1000.0, 4000.0])
    assert Speed().total_duration_s == 130.0


def test_segments_in_file(tmp_path):
    text = """
[speed]
start_rpm = 1000.0
segments = [
    {duration_s = 30.0, end_rpm = 2500.0},
    {duration_s = 20, end_rpm = 2500},
]
"""
    s = load_scenario(_write(tmp_path, text))
    assert s.speed.segments == ((30.0, 2500.0), (20.0, 2500.0))
    assert s.speed.total_duration_s == 50.0


def test_model_source_resolved_against_file_dir(tmp_path):
    sub = tmp_path / "cases"
    sub.mkdir()
    path = _write(sub, '[model]\nsource = "models/disk.npz"\n')
    assert load_scenario(path).model.source == str(sub / "models" / "disk.npz")
    path = _write(sub, '[model]\nsource = "builtin"\n')
    assert load_scenario(path).model.source == "builtin"
    # programmatic construction stores the string as given
    assert Model(source="rel/disk.npz").source == "rel/disk.npz"


def test_speed_initial_round_trip_and_default_text(tmp_path):
    """``[speed] initial``: "steady" by default and not written then (a default scenario's text,
    and so its run id, is what it was); "rest" round-trips."""
    assert Scenario().speed.initial == "steady"
    assert "initial" not in dumps_toml(Scenario())
    assert 'initial = "steady"' in dumps_toml(Scenario(), comments=True)
    s = scenario_from_dict({"speed": {"initial": "rest"}})
    text = dumps_toml(s)
    assert 'initial = "rest"' in text
    _assert_same(load_scenario(_write(tmp_path, text)), s)


# ----------------------------------------------------------------------------- errors

BAD = [
    pytest.param("[speed]\nstart_rmp = 1000.0\n", ["unknown key [speed] start_rmp"],
                 id="unknown key"),
    pytest.param("[spede]\nstart_rpm = 1000.0\n", ["unknown section [spede]"],
                 id="unknown section"),
    pytest.param('[speed]\ninitial = "still"\n', ['[speed] initial must be one of "steady", "rest", got "still"'],
                 id="speed initial"),
    pytest.param("[[excitation]]\nengine_ordr = 3\n",
                 ["unknown key [[excitation]][0] engine_ordr"], id="unknown excitation key"),
    pytest.param('[speed]\nstart_rpm = "fast"\n', ["[speed] start_rpm", "string"],
                 id="string for float"),
    pytest.param("[model]\ndamping_beta_s = true\n", ["[model] damping_beta_s", "boolean"],
                 id="bool for float"),
    pytest.param("[rotor]\nn_blades = true\n", ["[rotor] n_blades", "boolean"],
                 id="bool for int"),
    pytest.param("[rotor]\nn_blades = 29.0\n", ["[rotor] n_blades", "float"],
                 id="float for int"),
    pytest.param("[toa]\naxial_interpolation = 1\n", ["[toa] axial_interpolation"],
                 id="int for bool"),
    pytest.param('[toa]\nmethod = "hp"\n', ["[toa] method"], id="bad choice"),
    pytest.param("[speed]\nstart_rpm = -1000.0\n", ["[speed] start_rpm must be in [0.001, 1e+06], got -1000.0"],
                 id="negative speed"),
    pytest.param("[rotor]\nn_blades = 1000\n", ["[rotor] n_blades must be an integer in [2, 200], got 1000"],
                 id="too many blades"),
    pytest.param("[[excitation]]\nengine_order = 4294967296\n", ["engine_order must be an integer in [1, 1000]"],
                 id="engine order beyond 1000"),
    pytest.param("[speed]\nduration_s = 1e9\n", ["[speed] makes", "revolutions"], id="endless run"),
    pytest.param("[speed]\nduration_s = 1e308\n", ["[speed] duration_s must be in [0.001, 1e+09], got 1e+308"],
                 id="duration beyond float arithmetic"),
    pytest.param("[speed]\nsegments = [{duration_s = 5e-324, end_rpm = 2000.0}]\n",
                 ["[speed] segments[0].duration_s must be in [0.001, 1e+09], got 5e-324"], id="subnormal segment"),
    pytest.param("[speed]\nstart_rpm = " + "9" * 400 + "\n", ["start_rpm must be finite"], id="huge integer"),
    pytest.param("[run]\nseed = " + "9" * 30 + "\n", ["[run] seed must be an integer in [0, "], id="huge seed"),
    pytest.param("[acquisition]\nclock_hz = 1e-300\n", ["[acquisition] clock_hz must be 0"], id="clock too slow"),
    pytest.param("[acquisition]\ntrigger_jitter_s = 1.0\n", ["1 % of the shortest revolution"], id="huge jitter"),
    pytest.param("[acquisition]\nspeed_fluctuation_rpm = 500.0\n", ["10 % of the slowest"],
                 id="huge fluctuation"),
    pytest.param("[rotor]\ntip_radius_m = 1e300\n", ["[rotor] tip_radius_m must be in (0, 10]"], id="huge radius"),
    pytest.param("[rotor]\nn_blades = 0\n", ["[rotor] n_blades must be an integer in [2, 200], got 0"],
                 id="zero blades"),
    pytest.param("[probes]\nangles_deg = [5.0, 15.15, nan]\n",
                 ["[probes] angles_deg[2] must be finite, got nan"], id="nan probe angle"),
    pytest.param("[probes]\nangles_deg = [5.0, 360.0]\n", ["[probes] angles_deg[1]"],
                 id="probe angle 360"),
    pytest.param("[probes]\nangles_deg = [5.0, 7.0, 5.0]\n", ["[probes] angles_deg[2]"],
                 id="duplicate probe angle"),
    pytest.param("[probes]\nangles_deg = []\n", ["[probes] angles_deg"], id="no probes"),
    pytest.param("[probes]\naxial_position_m = 0.02\n", ["[probes] axial_position_m"],
                 id="probe z outside chord"),
    pytest.param("[rotor]\nstagger_deg = 10.0\n", ["[probes] axial_position_m"],
                 id="chord too short for probe z"),
    pytest.param("[[excitation]]\nnodal_diameter = 29\n",
                 ["[[excitation]][0] nodal_diameter", "n_blades"], id="ND >= n_blades"),
    pytest.param("[[excitation]]\n[[excitation]]\nengine_order = 0\n",
                 ["[[excitation]][1] engine_order"], id="second excitation bad"),
    pytest.param("[[excitation]]\ndirection = [0, 0, 0]\n", ["[[excitation]][0] direction"],
                 id="zero direction"),
    pytest.param("excitation = []\n", ["[[excitation]]"], id="no excitation"),
    pytest.param("[excitation]\nengine_order = 8\n", ["excitation", "array of tables"],
                 id="excitation as table"),
    pytest.param("[model]\nstiffness_factors = [1.0, 1.01]\n",
                 ["[model] stiffness_factors", "29"], id="mistuning list wrong length"),
    pytest.param("[model]\nmass_std = 0.01\nmass_factors = " + str([1.0] * 29) + "\n",
                 ["[model] mass_std"], id="mistuning factors and std"),
    pytest.param("[rotor]\nnominal_node = 10\n", ["[rotor] nominal_node"],
                 id="nominal node beyond nodes"),
    pytest.param("[rotor]\nn_tip_nodes = 100\n", ["[rotor] tip_node_spacing_m"],
                 id="tip nodes beyond chord"),
    pytest.param('[run]\nrig = "rig 1"\n', ["[run] rig"], id="bad rig name"),
    pytest.param("[speed\nstart_rpm = 1\n", ["malformed TOML"], id="malformed TOML"),
    pytest.param(None, ["no such file"], id="missing file"),
    pytest.param("[speed]\nend_rpm = 3000.0\nsegments = [{duration_s = 1.0, end_rpm = 2.0}]\n",
                 ["[speed] end_rpm", "segments"], id="segments with end_rpm"),
    pytest.param("[speed]\nsegments = [{duration_s = -1.0, end_rpm = 2.0}]\n",
                 ["[speed] segments[0].duration_s"], id="negative segment duration"),
    pytest.param("[speed]\nsegments = [{duration_s = 1.0}]\n",
                 ["[speed] segments[0]", "end_rpm"], id="segment missing key"),
    pytest.param("seed = 3\n", ["unknown top-level key seed", "[run]"], id="top-level key"),
]


@pytest.mark.parametrize("text, expected", BAD)
def test_bad_input_names_the_field(tmp_path, text, expected):
    path = tmp_path / "scenario.toml"
    if text is not None:
        path.write_text(text, encoding="utf-8")
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    msg = str(info.value)
    assert isinstance(info.value, BttsimError)
    assert msg.startswith(f"{path}: "), msg
    assert "\n" not in msg
    for part in expected:
        assert part in msg, msg


def test_directory_and_non_utf8(tmp_path):
    with pytest.raises(ScenarioError, match="is a directory"):
        load_scenario(tmp_path)
    path = tmp_path / "latin1.toml"
    path.write_bytes('[run]\nrig = "r\xe9"\n'.encode("latin-1"))
    with pytest.raises(ScenarioError, match="UTF-8"):
        load_scenario(path)


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root reads anything")
def test_unreadable_file(tmp_path):
    path = _write(tmp_path, "")
    path.chmod(0)
    try:
        with pytest.raises(ScenarioError, match="permission denied"):
            load_scenario(path)
    finally:
        path.chmod(0o644)


def test_programmatic_construction_is_validated():
    with pytest.raises(ScenarioError, match=r"\[rotor\] n_blades"):
        Rotor(n_blades=0)
    with pytest.raises(ScenarioError, match=r"nodal_diameter"):
        Scenario(rotor=Rotor(n_blades=4), excitation=(Excitation(nodal_diameter=4),))
    with pytest.raises(ScenarioError, match=r"\[\[excitation\]\]"):
        Scenario(excitation=())
    with pytest.raises(ScenarioError, match=r"\[probes\] angles_deg\[0\]"):
        Probes(angles_deg=[float("inf")])
    with pytest.raises(ScenarioError, match=r"\[speed\] end_rpm"):
        Speed(end_rpm=np.nan)
    with pytest.raises(ScenarioError, match=r"\[model\] disk_asymmetry"):
        Model(disk_asymmetry=1)
    with pytest.raises(ScenarioError, match=r"\[run\] seed"):
        Run(seed=-1)
    assert scenario_from_dict({}) == Scenario()
    with pytest.raises(ScenarioError, match=r"^<dict>: \[run\] seed"):
        scenario_from_dict({"run": {"seed": 1.5}})


# ----------------------------------------------------------------------------- CLI


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "bttsim_stream.cli", *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=60)


def test_cli_prints_default_scenario(tmp_path):
    res = _cli("scenario")
    assert res.returncode == 0, res.stderr
    assert res.stdout == default_toml()
    _assert_same(load_scenario(_write(tmp_path, res.stdout)), Scenario())


def test_cli_check_bad_file(tmp_path):
    path = _write(tmp_path, "[rotor]\nn_blades = 0\n", name="bad.toml")
    res = _cli("scenario", "--check", str(path))
    assert res.returncode == 2
    lines = res.stderr.splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("bttsim: error:")
    assert "[rotor] n_blades" in lines[0]
    ok = _cli("scenario", "--check", str(_write(tmp_path, default_toml(), name="ok.toml")))
    assert ok.returncode == 0 and "ok" in ok.stdout


def test_probe_axial_position_is_checked_against_a_user_models_tip_nodes(tmp_path):
    """With a user's model the tip nodes, not ``[rotor]``, bound the probe's axial position:
    a model built with a 30 mm chord at 60 deg stagger (axial extent 26 mm) takes a probe at
    24 mm (its tip nodes span 23-26 mm) that the default ``[rotor]`` (about 13 mm) would refuse; a
    probe beyond its nodes is one line naming them."""
    from bttsim_stream.model.modal_model import build_model, save_model
    from bttsim_stream.sim.core import RunUpSimulator
    from bttsim_stream.scenario import scenario_from_dict

    wide = scenario_from_dict({"rotor": {"tip_chord_m": 0.03, "stagger_deg": 60.0},
                               "probes": {"axial_position_m": 0.024}})
    path = tmp_path / "wide.npz"
    save_model(build_model(wide), path)
    z_max = float(np.max(np.load(path, allow_pickle=False)["tip_ref"][..., 2]))
    assert z_max == pytest.approx(0.03 * np.sin(np.deg2rad(60.0)), rel=1e-9)
    assert Scenario().rotor.tip_axial_extent_m < 0.0135

    with pytest.raises(ScenarioError, match=r"\[probes\] axial_position_m"):
        scenario_from_dict({"probes": {"axial_position_m": 0.024}})  # the built-in model: [rotor]
    scn = scenario_from_dict({"model": {"source": str(path)}, "probes": {"axial_position_m": 0.024}})
    sim = RunUpSimulator(scn, n_revolutions=1)
    assert sim.z_probe == 0.024
    far = scenario_from_dict({"model": {"source": str(path)}, "probes": {"axial_position_m": 0.027}})
    with pytest.raises(BttsimError, match="outside the model's tip nodes") as err:
        RunUpSimulator(far, n_revolutions=1)
    assert "\n" not in str(err.value)


# --------------------------------------------------------------------------------------
# One declaration per field
# --------------------------------------------------------------------------------------


def test_schema_md_field_tables_are_generated():
    """schemas/scenario.md's tables are what the declarations give; regenerate them with
    ``python -m bttsim_stream.scenario --schema-md schemas/scenario.md``."""
    from bttsim_stream.scenario import OPTIONAL_ARRAYS, schema_markdown

    path = Path(__file__).resolve().parents[1] / "schemas" / "scenario.md"
    text = path.read_text(encoding="utf-8")
    assert schema_markdown(text) == text, "run: python -m bttsim_stream.scenario --schema-md schemas/scenario.md"
    for name in [*SECTIONS, *OPTIONAL_ARRAYS, "acquisition.signal"]:
        assert f"<!-- fields: {name} " in text, f"no generated table for [{name}]"


@pytest.mark.parametrize("cls, name, shown", [
    (Rotor, "tip_chord_m", "in (0, tip_radius_m]"),
    (Rotor, "n_blades", "integer in [2, 200]"),
    (Speed, "segments", "{duration_s (s, in [0.001, 1e9]),\nend_rpm (rpm, in [0.001, 1e6])}"),
    (Signal, "sample_rate_hz", "Hz; in [1e5, 1e9]"),
], ids=["sibling bound", "integer", "segment members", "unit and range"])
def test_comment_docstring_and_schema_show_the_declared_bounds(cls, name, shown):
    from bttsim_stream.fieldspec import markdown_table

    assert shown in comments(cls)[name]
    flat = " ".join(shown.split())
    assert flat in " ".join(cls.__doc__.split())
    assert flat in markdown_table(cls)


@pytest.mark.parametrize("options", [
    dict(kind="float", lo=0, doc="no bounds shown"),
    dict(kind="float", unit="m", doc="no unit shown; {range}"),
    dict(kind="str", choices=("a", "b"), doc='only "a"'),
], ids=["bounds", "unit", "choices"])
def test_a_declaration_must_show_its_bounds(options):
    from bttsim_stream.fieldspec import spec

    with pytest.raises(ValueError):
        spec(0.0, **options)


def test_a_bound_from_a_sibling_is_named():
    with pytest.raises(ScenarioError, match=r"^\[rotor\] tip_chord_m must be in \(0, tip_radius_m = 0.19\], got 0.5$"):
        Rotor(tip_chord_m=0.5)
    with pytest.raises(ScenarioError, match=r"^\[rotor\] nominal_node must be <= n_tip_nodes = 9, got 10$"):
        Rotor(nominal_node=10)


def test_schema_md_command_checks_and_rewrites(tmp_path):
    from bttsim_stream.scenario import main

    path = tmp_path / "s.md"
    path.write_text("# x\n\n<!-- fields: toa (generated) -->\nstale\n<!-- end fields -->\n")
    assert main(["--schema-md", str(path), "--check"]) == 1
    assert main(["--schema-md", str(path)]) == 0
    assert "| `grid_step_s` | s | `1.2e-05` |" in path.read_text()
    assert main(["--schema-md", str(path), "--check"]) == 0
