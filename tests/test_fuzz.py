"""Issue 16: a bounded, seeded fuzz of every input the CLI reads -- scenario TOML, model
``.npz``, CalculiX ``.frd`` results, MCAP bytes and well-formed MCAP files with wrong content (raw
probe signals and double pulses included) -- ends in 0 tracebacks and 0 hangs.

Every case runs ``bttsim`` in-process (:func:`bttsim_stream.cli.main`, a few through a real
subprocess) under a per-case alarm, and must end with

* exit status 0 (the output is an honest answer: a checked scenario, a written file, a
  resonance table or "NO RESONANCE FOUND"; a NaN or an absurd amplitude in a table comes with a
  ``bttsim: warning:`` line), 2 (bad input: one line ``bttsim: error: ...``) or 3 (an
  incomplete result, said so);
* no traceback, no exception escaping ``main``;
* within :data:`CASE_TIMEOUT_S`.

The generator is seeded (:data:`SEED`): a failure names its case (kind, number, mutation), and
the same seed gives the same cases. About 650 cases, 50-80 s on a loaded 2-core machine.
"""

from __future__ import annotations

import contextlib
import gc
import io
import json
import math
import os
import random
import re
import signal
import subprocess
import sys
import time
import traceback
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from bttsim_stream import cli
from bttsim_stream.bus import codec, keys
from bttsim_stream.bus._gen.bttsim.v1 import bttsim_pb2 as pb
from bttsim_stream.bus.recording import McapRecorder, read_recording
from bttsim_stream.bus.stream import Message
from bttsim_stream.errors import BttsimError
from bttsim_stream.model import build_model, save_model
from bttsim_stream.scenario import Scenario, scenario_from_dict, scenario_to_dict

pytestmark = pytest.mark.slow

#: Fixed; ``BTTSIM_FUZZ_SEED=N`` explores other cases (a failure prints its seed).
SEED = int(os.environ.get("BTTSIM_FUZZ_SEED", "16"))
#: A case that takes longer than this is a hang, s (the slowest honest case takes about 1 s).
CASE_TIMEOUT_S = 60.0
#: Exit statuses and their meaning (``bttsim --help`` and the README say the same).
EXIT_MEANING = {0: "ok", 2: "bad input (one line)", 3: "incomplete result (said so)"}

BASE_TOML = ("[speed]\nstart_rpm = 2450.0\nsegments = [{duration_s = 4.0, end_rpm = 2700.0}]\n")
N_TOML, N_TOML_TEXT, N_SIMULATE = 130, 30, 20
N_NPZ, N_NPZ_PLOT = 45, 6
N_MCAP_BYTES, N_MCAP_CONTENT, N_VIEW = 50, 110, 24
N_SUBPROCESS = 6
N_SIGNAL = 24
N_FRD = 200
N_EXTREME = 90
#: The base run with the probe signal chain on, its raw windows published, and double pulses
#: (no hysteresis on a noisy pulse): the fields a forger of signals and extra edges aims at.
SIGNAL_TOML = BASE_TOML + ("[acquisition]\nclock_hz = 1e8\n[acquisition.signal]\nenabled = true\npublish = true\n"
                           "hysteresis_v = 0.0\nnoise_v = 0.02\n")


# --------------------------------------------------------------------------------------
# Running one case
# --------------------------------------------------------------------------------------


class _Hang(BaseException):
    """Raised by the alarm: a BaseException, so that no ``except Exception`` swallows it."""


@dataclass
class Outcome:
    case: str
    argv: list
    status: int | None
    out: str
    err: str
    problem: str | None = None


def _alarm(_signum, _frame):
    raise _Hang()


@pytest.fixture(autouse=True, scope="module")
def _collected():
    """What earlier tests left to the garbage collector (an unclosed pipe) is collected before
    the cases run, so that its ResourceWarning is not taken for a case's."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ResourceWarning)
        gc.collect()


def run_case(case: str, argv: list) -> Outcome:
    """``bttsim argv`` in-process; the problem (traceback, hang, bad status) if any."""
    out, err = io.StringIO(), io.StringIO()
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, CASE_TIMEOUT_S)
    status, problem = None, None
    try:
        # warnings as a console shows them (pytest would otherwise record them out of sight)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings.showwarning = lambda m, c, f, n, file=None, line=None: err.write(
                warnings.formatwarning(m, c, f, n, line))
            try:
                status = cli.main([str(a) for a in argv])
            except SystemExit as exc:  # argparse
                status = exc.code if isinstance(exc.code, int) else 2
            except _Hang:
                problem = f"hang: no answer within {CASE_TIMEOUT_S:g} s"
            except BaseException:  # noqa: BLE001 - any escape is the failure under test
                problem = "traceback:\n" + traceback.format_exc(limit=-6)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    o = Outcome(case, list(argv), status, out.getvalue(), err.getvalue(), problem)
    if o.problem is None:
        o.problem = judge(o)
    return o


_NAN_WORD = re.compile(r"\bnan\b", re.IGNORECASE)


def judge(o: Outcome) -> str | None:
    """What is wrong with a finished case (None: nothing)."""
    if "Traceback (most recent call last)" in o.err:
        return "traceback on stderr"
    if o.status not in EXIT_MEANING:
        return f"exit status {o.status!r} (allowed: {EXIT_MEANING})"
    errors = [ln for ln in o.err.splitlines() if ln.startswith("bttsim: error:")]
    if o.status == 2 and len(errors) != 1:
        return f"exit status 2 with {len(errors)} 'bttsim: error:' lines"
    if o.status == 0 and errors:
        return "exit status 0 after an error line"
    if o.status == 0 and o.argv[0] == "process":
        if not re.search(r"^(RESONANCE|STEADY|NO RESONANCE FOUND)", o.out, re.MULTILINE):
            return "exit status 0 without a result"
        table = [ln for ln in o.out.splitlines() if not ln.startswith(("note:", "zeroing:", "NO RESONANCE"))]
        if any(_NAN_WORD.search(ln) for ln in table) and "bttsim: warning:" not in o.err:
            return "NaN in the result table without a warning"
    return None


def report(outcomes: list[Outcome]) -> str:
    bad = [o for o in outcomes if o.problem]
    lines = [f"{len(bad)} of {len(outcomes)} fuzz cases failed (seed {SEED}):"]
    for o in bad[:12]:
        lines.append(f"--- {o.case}: bttsim {' '.join(map(str, o.argv))}\n    {o.problem}\n"
                     f"    status {o.status}; stderr tail: {o.err[-600:]!r}")
    return "\n".join(lines)


def _tally(outcomes) -> dict:
    counts: dict = {}
    for o in outcomes:
        counts[o.status] = counts.get(o.status, 0) + 1
    return counts


# --------------------------------------------------------------------------------------
# Scenario TOML
# --------------------------------------------------------------------------------------

#: Magnitudes at the ends of the float range (the largest, the smallest subnormal, a signed zero).
_MAGNITUDES = [1e308, -1e308, 1.7976931348623157e308, 5e-324, -5e-324, -0.0]
_NASTY = [0, -1, 1, 2, 3, 7, 1000, 1001, 2**31, 2**32, 2**63 - 1, -(2**63), 0.0, -0.0, 1e-300, 5e-324, 1e300,
          -1e300, 1e308, -1e308, 1e6, 1e9, math.nan, math.inf, -math.inf, 0.5, 359.9999, 360.0, True, False, "", "x",
          "builtin", "leading_edge", "HP", "rig 1", [], [0.0], [1e300, 2.0, 3.0], [[1]], [1, "a"], {}, {"a": 1},
          {"duration_s": 1e-300, "end_rpm": 2500.0}]


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))} = {_toml_value(x)}" for k, x in v.items()) + "}"
    return "[" + ", ".join(_toml_value(x) for x in v) + "]"


def dumps(d: dict) -> str:
    """TOML for any mix of tables, arrays of tables and stray top-level values."""
    top = [f"{json.dumps(str(k))} = {_toml_value(v)}" for k, v in d.items()
           if not isinstance(v, dict) and not (isinstance(v, list) and v and all(isinstance(x, dict) for x in v))]
    lines = top[:]
    for k, v in d.items():
        if isinstance(v, dict):
            lines.append(f"[{json.dumps(str(k))}]")
            lines += [f"{json.dumps(str(a))} = {_toml_value(b)}" for a, b in v.items()]
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for entry in v:
                lines.append(f"[[{json.dumps(str(k))}]]")
                lines += [f"{json.dumps(str(a))} = {_toml_value(b)}" for a, b in entry.items()]
    return "\n".join(lines) + "\n"


def _nasty_number(rng: random.Random, v):
    if isinstance(v, (int, float)) and not isinstance(v, bool) and rng.random() < 0.4:
        scale = rng.choice([-1, 0, 1e-9, 1e-3, 0.5, 2, 10, 1e3, 1e6, 1e300, 1e308, 5e-324])
        x = v * scale
        return int(x) if isinstance(v, int) and abs(x) < 2**62 else float(x)
    return rng.choice(_NASTY)


def mutate_scenario(rng: random.Random, base: dict) -> tuple[dict, str]:
    d = json.loads(json.dumps(base))  # deep copy (plain types only)
    what = []
    for _ in range(rng.choice([1, 1, 2, 3])):
        sections = [s for s in d if isinstance(d[s], dict)]
        op = rng.random()
        if op < 0.55 and sections:
            s = rng.choice(sections)
            if not d[s]:
                continue
            k = rng.choice(sorted(d[s]))
            d[s][k] = _nasty_number(rng, d[s][k])
            what.append(f"[{s}] {k} = {_toml_value(d[s][k])[:40]}")
        elif op < 0.7:
            exc = d.get("excitation")
            if isinstance(exc, list) and exc and isinstance(exc[0], dict):
                e = dict(exc[0])
                k = rng.choice(sorted(e))
                e[k] = _nasty_number(rng, e[k])
                exc.append(e) if rng.random() < 0.5 else exc.__setitem__(0, e)
                what.append(f"[[excitation]] {k} = {_toml_value(e[k])[:40]}")
        elif op < 0.78 and sections:
            s = rng.choice(sections)
            if d[s]:
                k = rng.choice(sorted(d[s]))
                del d[s][k]
                what.append(f"drop [{s}] {k}")
        elif op < 0.84:
            s = rng.choice(sorted(d))
            del d[s]
            what.append(f"drop [{s}]")
        elif op < 0.9:
            s = rng.choice(sorted(d) + ["bogus"])
            d[s] = rng.choice([1, "x", [], [1, 2], {"nope": 1}])
            what.append(f"{s} = {_toml_value(d[s])}")
        else:
            n = rng.choice([0, 1, 3, 40])
            segs = [{"duration_s": _nasty_number(rng, 1.0), "end_rpm": _nasty_number(rng, 2500.0)} for _ in range(n)]
            d.setdefault("speed", {})
            if isinstance(d["speed"], dict):
                d["speed"] = {"start_rpm": d["speed"].get("start_rpm", 2450.0), "segments": segs}
                what.append(f"[speed] {n} random segments")
    return d, "; ".join(what) or "unchanged"


def mutate_text(rng: random.Random, text: str) -> tuple[bytes, str]:
    data = bytearray(text.encode())
    op = rng.randrange(6)
    if op == 0:
        n = rng.randrange(len(data))
        return bytes(data[:n]), f"cut at byte {n}"
    if op == 1:
        for _ in range(rng.randint(1, 6)):
            data[rng.randrange(len(data))] = rng.randrange(256)
        return bytes(data), "random bytes"
    if op == 2:
        return b"\xff\xfe" + bytes(data), "not UTF-8"
    if op == 3:
        lines = text.splitlines()
        i = rng.randrange(len(lines))
        return ("\n".join(lines[:i + 1] + lines[i:]) + "\n").encode(), f"line {i} twice"
    if op == 4:
        return f"[speed]\nstart_rpm = {'9' * rng.choice([20, 400])}\n".encode(), "huge literal"
    return bytes(rng.randrange(256) for _ in range(rng.randint(0, 200))), "random file"


def _fits_a_quick_simulation(path: Path) -> bool:
    """A scenario that checked out and is small enough to simulate here (the limits allow
    runs of hours; the fuzz simulates only short ones)."""
    from bttsim_stream.scenario import load_scenario

    scn = load_scenario(path)
    t, rpm = scn.speed.breakpoints()
    revs = float(np.sum(0.5 * (rpm[:-1] + rpm[1:]) * np.diff(t))) / 60.0
    return (revs <= 600 and scn.rotor.n_blades * scn.model.n_families <= 300 and len(scn.excitation) <= 3
            and scn.toa.grid_step_s >= 1e-7)


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


@pytest.fixture(scope="module")
def base_mcap(workdir):
    toml = workdir / "base.toml"
    toml.write_text(BASE_TOML)
    path = workdir / "base.mcap"
    o = run_case("base", ["simulate", toml, "--out", path, "-q"])
    assert o.status == 0 and not o.problem, o.err
    return path


@pytest.fixture(scope="module")
def processed_mcap(workdir, base_mcap):
    from bttsim_stream.offline import with_processing

    return Path(with_processing(base_mcap, workdir / "processed.mcap"))


def test_fuzz_scenario_toml(workdir):
    rng = random.Random(SEED)
    base = scenario_to_dict(scenario_from_dict({"speed": {"start_rpm": 2450.0,
                                                          "segments": [{"duration_s": 4.0, "end_rpm": 2700.0}]}}))
    outcomes, passed = [], []
    t0 = time.perf_counter()
    for i in range(N_TOML + N_TOML_TEXT):
        path = workdir / f"s{i}.toml"
        if i < N_TOML:
            d, what = mutate_scenario(rng, base)
            path.write_text(dumps(d))
        else:
            data, what = mutate_text(rng, BASE_TOML + dumps({"probes": base["probes"]}))
            path.write_bytes(data)
        o = run_case(f"toml #{i} ({what})", ["scenario", "--check", path])
        _one_line(o)
        outcomes.append(o)
        if o.status == 0 and not o.problem and _fits_a_quick_simulation(path):
            passed.append((o.case, path))
    for case, path in rng.sample(passed, min(N_SIMULATE, len(passed))):
        outcomes.append(run_case(f"simulate {case}", ["simulate", path, "--out", path.with_suffix(".mcap"), "-q"]))
    tally = _tally(outcomes)
    print(f"toml: {len(outcomes)} cases ({len(passed)} checked out), statuses {tally}, "
          f"{time.perf_counter() - t0:.1f} s")
    assert not any(o.problem for o in outcomes), report(outcomes)
    assert tally.get(2, 0) > len(outcomes) // 3 and tally.get(0, 0) > 10, tally  # the fuzz reaches both sides


def _one_line(o: Outcome) -> None:
    """A refusal (status 2) is its one error line and nothing else on stderr: no numpy
    warning printed on the way to it."""
    if o.problem is None and o.status == 2 and len(o.err.strip().splitlines()) != 1:
        o.problem = f"exit status 2 with {len(o.err.strip().splitlines())} lines on stderr (one expected)"


def _numeric_fields(d: dict):
    """``(label, setter)`` of every number (and the first of every number array) of a scenario dict."""
    def num(v):
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    for s, sec in d.items():
        tables = [(f"[{s}]", sec)] if isinstance(sec, dict) else [(f"[[{s}]]", t) for t in sec[:1]]
        for label, table in tables:
            for k, v in table.items():
                if num(v):
                    yield f"{label} {k}", (lambda t, k=k: lambda x: t.__setitem__(k, x))
                elif isinstance(v, list) and v and all(num(a) for a in v):
                    yield f"{label} {k}[0]", (lambda t, k=k: lambda x: t[k].__setitem__(0, x))
                elif isinstance(v, list) and v and all(isinstance(a, dict) for a in v):
                    for sk in sorted(v[0]):  # every segment's member at once
                        yield f"{label} {k}[].{sk}", (lambda t, k=k, sk=sk: lambda x: [g.__setitem__(sk, x)
                                                                                       for g in t[k]])


def _path_in(d: dict, label: str) -> dict:
    """The table of ``d`` that ``label`` (``[s] key`` or ``[[s]] key``) lives in."""
    s = label.split("]")[0].strip("[")
    return d[s] if isinstance(d[s], dict) else d[s][0]


def test_fuzz_scenario_magnitudes(workdir):
    """Every number of a scenario (the default run-up, and a segmented one) at the ends of the
    float range: a checked scenario or exactly one stderr line, never a numpy warning."""
    outcomes = []
    bases = {"run-up": {}, "segments": {"speed": {"start_rpm": 2450.0, "segments": [
        {"duration_s": 4.0, "end_rpm": 2700.0}, {"duration_s": 1.0, "end_rpm": 2700.0}]}}}
    for name, partial in bases.items():
        base = scenario_to_dict(scenario_from_dict(partial))
        for label, setter in list(_numeric_fields(base)):
            for x in _MAGNITUDES:
                d = json.loads(json.dumps(base))
                setter(_path_in(d, label))(x)
                path = workdir / f"mag-{len(outcomes)}.toml"
                path.write_text(dumps(d))
                o = run_case(f"{name}: {label} = {x!r}", ["scenario", "--check", path])
                _one_line(o)
                outcomes.append(o)
    tally = _tally(outcomes)
    print(f"scenario magnitudes: {len(outcomes)} cases, statuses {tally}")
    assert not any(o.problem for o in outcomes), report(outcomes)
    assert tally.get(2, 0) > len(outcomes) // 3, tally


# --------------------------------------------------------------------------------------
# Model .npz
# --------------------------------------------------------------------------------------


def _save(path: Path, arrays: dict) -> None:
    with open(path, "wb") as f:
        np.savez(f, **arrays)  # object arrays are pickled: the loader must refuse them


def mutate_model(rng: random.Random, arrays: dict, path: Path) -> str:
    a = dict(arrays)
    op = rng.randrange(10)
    names = sorted(a)
    k = rng.choice([n for n in names if n != "meta"] if op == 3 else names)
    v = np.asarray(a[k])
    if op == 0:
        del a[k]
        what = f"drop {k}"
    elif op == 1:
        a[rng.choice(["bogus", "family", "nodal_diameter", "blade_alone_freq_hz", "campbell_freq_hz"])] = \
            rng.choice([np.zeros(0), np.arange(3), np.full((2, 2), -1.0), np.array([2**62]), np.array([1e300])])
        what = "add/replace an optional array"
    elif op == 2 and v.ndim:
        a[k] = rng.choice([v.T, v[:1], v[..., :1], v.reshape(-1), v[None]])
        what = f"{k} reshaped"
    elif op == 3:
        a[k] = v.astype(rng.choice([np.int32, np.complex128, np.bool_, np.float16, "U3"]))
        what = f"{k} as another dtype"
    elif op == 4:
        a[k] = np.array([{"x": 1}, None], dtype=object)
        what = f"{k} an object array (pickled)"
    elif op == 5 and v.dtype.kind == "f" and v.size:
        w = v.copy()
        w.flat[rng.randrange(w.size)] = rng.choice([math.nan, math.inf, -1.0, 0.0, 1e300])
        a[k] = w
        what = f"{k} one bad value"
    elif op == 6:
        meta = json.loads(str(a["meta"]))
        key = rng.choice(["schema", "schema_version", "n_blades", "nominal_node", "stagger_deg", "provenance"])
        meta[key] = rng.choice([None, "41.5", -1, 0, 90, 1e300, True, [], {}, 10**6])
        a["meta"] = np.array(json.dumps(meta))
        what = f"meta.{key} = {meta[key]!r}"
    elif op == 7:
        a["meta"] = np.array(rng.choice(["{", "[]", "null", "{\"schema\": 1}"]))
        what = "meta not a model's JSON"
    else:
        _save(path, a)
        data = bytearray(path.read_bytes())
        if op == 8:
            n = rng.randrange(len(data))
            path.write_bytes(bytes(data[:n]))
            return f"cut at byte {n}"
        for _ in range(rng.randint(1, 16)):
            data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
        path.write_bytes(bytes(data))
        return "bit flips"
    _save(path, a)
    return what


def test_fuzz_model_npz(workdir, monkeypatch):
    rng = random.Random(SEED + 1)
    model = build_model(Scenario())
    good = workdir / "model.npz"
    save_model(model, good)
    with np.load(good, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    outcomes, loadable = [], []
    t0 = time.perf_counter()
    plotted = 0
    import bttsim_stream.model.report as report_mod  # `bttsim model show` imports the plot from there

    real_plot = report_mod.plot_family_frequencies
    for i in range(N_NPZ):
        path = workdir / f"m{i}.npz"
        what = mutate_model(rng, arrays, path)
        plot = plotted < N_NPZ_PLOT and rng.random() < 0.3
        plotted += plot
        # the plot takes 0.3 s: most cases check the loading and the table only
        monkeypatch.setattr(report_mod, "plot_family_frequencies", real_plot if plot else (lambda m, png, *args: None))
        o = run_case(f"npz #{i} ({what})", ["model", "show", path, "--png", workdir / f"m{i}.png"])
        outcomes.append(o)
        if o.status == 0:
            loadable.append((o.case, path))
    monkeypatch.setattr(report_mod, "plot_family_frequencies", real_plot)
    for case, path in rng.sample(loadable, min(6, len(loadable))):  # the simulator on a user's model
        toml = path.with_suffix(".toml")
        toml.write_text(BASE_TOML + f"[model]\nsource = {json.dumps(str(path))}\n")
        outcomes.append(run_case(f"simulate with {case}", ["simulate", toml, "--out", path.with_suffix(".mcap"), "-q"]))
    tally = _tally(outcomes)
    print(f"npz: {len(outcomes)} cases, statuses {tally}, {time.perf_counter() - t0:.1f} s")
    assert not any(o.problem for o in outcomes), report(outcomes)
    assert tally.get(2, 0) > len(outcomes) // 2, tally


# --------------------------------------------------------------------------------------
# CalculiX .frd (``bttsim model import``)
# --------------------------------------------------------------------------------------

#: Hostile contents of one fixed-width field (E12.5 value, I5/I10 node number, header count).
_FRD_NUMBERS = ["abcdefghijkl", "nan", "-nan", "inf", "-inf", "1.0E+999", "-1.0E+999", "************", "1.2.3",
                "1e308", "-1e308", "5e-324", "", "0x10", "1_000", "+", "-", "E", "1.0E", "9" * 12, "-0.0"]
_FRD_INTS = ["x", "-1", "0", "1", "2", "99", "2147483648", "9999999999", "-9999999999", "1.5", "", "  1 2",
             str(2**63), "1e3"]


def _frd_field(line: str, start: int, width: int, token: str) -> str:
    """``line`` with columns [start, start + width) replaced by ``token`` (right-aligned, cut to width)."""
    line = line.ljust(start + width)
    return line[:start] + token.rjust(width)[-width:] + line[start + width:]


def mutate_frd(rng: random.Random, text: str) -> tuple[bytes, str]:
    """One or two hostile changes to a valid ``.frd`` file: a field's value, a header count or
    format flag, a component count, a parameter (1P) value, a cut, moved or repeated line, stray
    bytes."""
    lines = text.splitlines()
    what = []
    for _ in range(rng.choice([1, 1, 1, 2])):
        op = rng.randrange(12)
        data = [i for i, ln in enumerate(lines) if ln.startswith(" -1")]
        heads = [i for i, ln in enumerate(lines) if ln.lstrip().startswith(("2C", "100C"))]
        params = [i for i, ln in enumerate(lines) if ln.lstrip().startswith("1P")]
        comps = [i for i, ln in enumerate(lines) if ln.startswith(" -4")]
        if op == 0 and data:  # one value of a node or result line
            i, k = rng.choice(data), rng.randrange(3)
            tok = rng.choice(_FRD_NUMBERS)
            lines[i] = _frd_field(lines[i], 13 + 12 * k, 12, tok)
            what.append(f"line {i + 1} value {k} = {tok!r}")
        elif op == 1 and data:  # a node number (I10), or a short-format id in the long layout
            i = rng.choice(data)
            tok = rng.choice(_FRD_INTS + [lines[rng.choice(data)][3:13].strip()])
            lines[i] = _frd_field(lines[i], 3, rng.choice([10, 5]), tok)
            what.append(f"line {i + 1} node number {tok!r}")
        elif op == 2 and lines:
            i = rng.randrange(len(lines))
            n = rng.randrange(len(lines[i]) + 1)
            lines[i] = lines[i][:n]
            what.append(f"line {i + 1} cut at column {n}")
        elif op == 3 and heads:  # the node count of a block header (I12 at columns 25-36)
            i = rng.choice(heads)
            n = int(lines[i][24:36] or 0)
            tok = rng.choice([str(n + 1), str(max(n - 1, 0)), "0", "-1", str(10**11), "abc", ""])
            lines[i] = _frd_field(lines[i], 24, 12, tok)
            what.append(f"line {i + 1} count {tok!r}")
        elif op == 4 and heads:  # the format flag (0 short, 1 long, 2 binary)
            i = rng.choice(heads)
            tok = rng.choice(["0", "2", "x", " ", "9"])
            lines[i] = _frd_field(lines[i], 73, 2 if "100C" in lines[i] else 1, tok)
            what.append(f"line {i + 1} format flag {tok!r}")
        elif op == 5 and comps:  # the component count of a result block (I5 at columns 14-18)
            i = rng.choice(comps)
            tok = rng.choice(["0", "1", "2", "5", "99", "99999", "x", "-3"])
            lines[i] = _frd_field(lines[i], 13, 5, tok)
            what.append(f"line {i + 1} components {tok!r}")
        elif op == 6 and params:  # a parameter's value (1PHID, 1PMODE, 1PSTEP, 1PGM, 1PAX)
            i = rng.choice(params)
            head = lines[i][:10].rstrip()
            tok = rng.choice(_FRD_INTS + _FRD_NUMBERS + ["1 2", "0 0 0 0 0 0", "1 2 3 4 5 nan"])
            lines[i] = f"{head:<26}{tok:>10}"
            what.append(f"line {i + 1} {head.strip()} {tok!r}")
        elif op == 7 and heads:  # the value field of a header: a result's frequency
            i = rng.choice(heads)
            tok = rng.choice(_FRD_NUMBERS + ["-2134.35", "0"])
            lines[i] = _frd_field(lines[i], 12, 12, tok)
            what.append(f"line {i + 1} frequency {tok!r}")
        elif op == 8 and lines:
            i, j = rng.randrange(len(lines)), rng.randrange(len(lines))
            kind = rng.randrange(3)
            if kind == 0:
                del lines[i]
                what.append(f"line {i + 1} dropped")
            elif kind == 1:
                lines.insert(j, lines[i])
                what.append(f"line {i + 1} repeated at {j + 1}")
            else:
                lines[i], lines[j] = lines[j], lines[i]
                what.append(f"lines {i + 1} and {j + 1} swapped")
        elif op == 9 and lines:  # a stray line, or junk at the end of one
            i = rng.randrange(len(lines))
            if rng.random() < 0.5:
                tok = rng.choice([" -1", " -3", " -4", " -5", "    2C", "  100C", "    3C", " 9999", "garbage",
                                  " -1        11" + " 1.00000E+00" * 7, "    1PHID"])
                lines.insert(i, tok)
                what.append(f"stray line {tok[:20]!r} at {i + 1}")
            else:
                lines[i] += rng.choice([" 1.00000E+00", "xyz", " " * 80])
                what.append(f"junk after line {i + 1}")
        elif op == 10:
            b = bytearray("\n".join(lines).encode())
            for _ in range(rng.randint(1, 6)):
                b[rng.randrange(len(b))] = rng.choice([rng.randrange(32, 127), rng.randrange(256)])
            return bytes(b), "; ".join(what + ["random bytes"])
        else:
            b = "\n".join(lines).encode()
            n = rng.randrange(len(b))
            return b[:n], "; ".join(what + [f"cut at byte {n}"])
    return ("\n".join(lines) + "\n").encode(), "; ".join(what) or "unchanged"


@pytest.fixture(scope="module")
def frd_text(workdir):
    """A small valid cyclic-symmetry ``.frd`` (7 sectors, 4 tip nodes 11-14, 2 families) in
    CalculiX's layout, from the exact spring-mass wheel of ``test_model_cyclic``."""
    from test_model_cyclic import _sector_solution, _spring_wheel
    from test_model_frd import N, _write_frd

    xyz, K, M = _spring_wheel(N)
    return _write_frd(workdir / "wheel.frd", _sector_solution(N, xyz, K, M, 2)).read_text()


#: ``bttsim model import`` of the fixture: the number of sectors and the nodes on the command line.
FRD_ARGS = ["--n-sectors", "7", "--tip-nodes", "11,12,13,14", "--force-node", "11", "--nominal-node", "1"]


def test_fuzz_frd(workdir, frd_text):
    rng = random.Random(SEED + 6)
    good = workdir / "wheel.frd"
    o = run_case("frd base", ["model", "import", good, *FRD_ARGS, "--out", workdir / "wheel.npz"])
    assert o.status == 0 and not o.problem, o.err
    outcomes = []
    t0 = time.perf_counter()
    for i in range(N_FRD):
        path = workdir / f"f{i}.frd"
        data, what = mutate_frd(rng, frd_text)
        path.write_bytes(data)
        o = run_case(f"frd #{i} ({what})", ["model", "import", path, *FRD_ARGS, "--out", path.with_suffix(".npz")])
        if o.problem is None and o.status == 2 and len(o.err.strip().splitlines()) != 1:
            o.problem = "exit status 2 with more than the one error line on stderr"
        if o.problem is None and o.status == 2 and path.with_suffix(".npz").exists():
            o.problem = "exit status 2 but the model file was written"
        outcomes.append(o)
    tally = _tally(outcomes)
    print(f"frd: {len(outcomes)} cases, statuses {tally}, {time.perf_counter() - t0:.1f} s")
    assert not any(o.problem for o in outcomes), report(outcomes)
    assert tally.get(2, 0) > len(outcomes) // 2 and tally.get(0, 0) > 5, tally  # the fuzz reaches both sides


# --------------------------------------------------------------------------------------
# MCAP bytes
# --------------------------------------------------------------------------------------


def mutate_bytes(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    b = bytearray(data)
    op = rng.randrange(6)
    if op == 0:
        n = rng.randrange(len(b))
        return bytes(b[:n]), f"cut at byte {n}"
    if op == 1:
        flips = rng.randint(1, 8)
        for _ in range(flips):
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
        return bytes(b), f"{flips} bit flip(s)"
    if op == 2:
        i, n = rng.randrange(len(b)), rng.randint(1, 64)
        b[i:i + n] = bytes(rng.randrange(256) for _ in range(n))
        return bytes(b), f"{n} random bytes at {i}"
    if op == 3:
        i, n = rng.randrange(len(b)), rng.randint(1, 4096)
        return bytes(b[:i] + b[i:i + n] + b[i:]), f"{n} bytes repeated at {i}"
    if op == 4:
        i, n = rng.randrange(len(b)), rng.randint(1, 4096)
        b[i:i + n] = bytes(min(n, len(b) - i))
        return bytes(b), f"{n} bytes zeroed at {i}"
    i = rng.randrange(8, len(b))  # a length field's worth of 0xff: a huge record length
    b[i:i + 8] = b"\xff" * 8
    return bytes(b), f"8 x 0xff at {i}"


def test_fuzz_mcap_bytes(workdir, base_mcap):
    rng = random.Random(SEED + 2)
    data = base_mcap.read_bytes()
    outcomes = []
    t0 = time.perf_counter()
    for i in range(N_MCAP_BYTES):
        path = workdir / f"b{i}.mcap"
        mutated, what = mutate_bytes(rng, data)
        path.write_bytes(mutated)
        outcomes.append(run_case(f"mcap bytes #{i} ({what})", ["process", path]))
    tally = _tally(outcomes)
    print(f"mcap bytes: {len(outcomes)} cases, statuses {tally}, {time.perf_counter() - t0:.1f} s")
    assert not any(o.problem for o in outcomes), report(outcomes)


# --------------------------------------------------------------------------------------
# Well-formed MCAP, wrong content
# --------------------------------------------------------------------------------------

_PB = {"meta": pb.RunMetadata, "opr": pb.Opr, "toa": pb.ToaBatch, "truth": pb.TruthBatch, "fit": pb.BladeFits,
       "tw": pb.TravellingWave, "resonance": pb.ResonanceReport, "signal": pb.SignalBatch}


def _nasty_scalar(rng: random.Random, f, value):
    t = f.type
    if t in (f.TYPE_DOUBLE, f.TYPE_FLOAT):
        return rng.choice([math.nan, math.inf, -math.inf, 0.0, -0.0, -1.0, 1e300, -1e300, 1e-300,
                           value * (1 + 1e-6) if isinstance(value, float) else 1.0, (value or 0) + 1.0,
                           (value or 0) - 1e3])
    if t in (f.TYPE_INT64, f.TYPE_SINT64, f.TYPE_SFIXED64):
        return rng.choice([0, -1, -5, 2**63 - 1, -(2**63), (value or 0) + 1, (value or 0) + 40, (value or 0) + 100000])
    if t in (f.TYPE_INT32, f.TYPE_SINT32, f.TYPE_SFIXED32, f.TYPE_ENUM):
        return rng.choice([0, -1, 2**31 - 1, -(2**31), 3])
    if t in (f.TYPE_UINT64, f.TYPE_FIXED64):
        return rng.choice([0, 1, 2**64 - 1, 2**62, (value or 0) + 1])
    if t in (f.TYPE_UINT32, f.TYPE_FIXED32):
        return rng.choice([0, 1, 2, 30, 99, 2**32 - 1, (value or 0) + 1])
    if t == f.TYPE_BOOL:
        return not value
    if t == f.TYPE_STRING:
        return rng.choice(["", "x" * 300, "rig/1", "é", "other-run"])
    return b"\x00\xff"


def mutate_proto(rng: random.Random, msg) -> str:
    """Set one field of ``msg`` (or of a nested message) to a hostile value, in place."""
    fields = [f for f in msg.DESCRIPTOR.fields]
    f = rng.choice(fields)
    if f.type == f.TYPE_MESSAGE:
        if codec.is_repeated(f):
            items = getattr(msg, f.name)
            if len(items) and rng.random() < 0.7:
                return f"{f.name}[].{mutate_proto(rng, items[rng.randrange(len(items))])}"
            if len(items):
                if rng.random() < 0.5:
                    del items[rng.randrange(len(items))]
                    return f"{f.name}: one removed"
                items.add().CopyFrom(items[0])
                return f"{f.name}: one repeated"
            return f"{f.name}: empty"
        return f"{f.name}.{mutate_proto(rng, getattr(msg, f.name))}"
    if codec.is_repeated(f):
        items = getattr(msg, f.name)
        op = rng.randrange(4)
        if op == 0:
            del items[:]
            return f"{f.name} cleared"
        if op == 1:
            items.append(_nasty_scalar(rng, f, items[-1] if len(items) else None))
            return f"{f.name} one more"
        if op == 2 and len(items):
            i = rng.randrange(len(items))
            items[i] = _nasty_scalar(rng, f, items[i])
            return f"{f.name}[{i}] = {items[i]!r}"[:80]
        if op == 3 and len(items):
            del items[-1]
            return f"{f.name} one fewer"
        return f"{f.name} unchanged"
    value = _nasty_scalar(rng, f, getattr(msg, f.name))
    setattr(msg, f.name, value)
    return f"{f.name} = {value!r}"[:80]


def forge(rng: random.Random, messages: list[Message], kinds) -> tuple[list[Message], str]:
    """A list of messages with one or two hostile changes (payloads, keys, order, numbers)."""
    msgs = list(messages)
    what = []
    for _ in range(rng.choice([1, 1, 2])):
        op = rng.random()
        idx = [i for i, m in enumerate(msgs) if keys.parse_key(m.key).kind in kinds]
        if not idx:
            break
        if op < 0.55:  # one field of one or of every message of a kind
            kind = rng.choice(sorted({keys.parse_key(msgs[i].key).kind for i in idx}))
            targets = [i for i in idx if keys.parse_key(msgs[i].key).kind == kind]
            every = rng.random() < 0.3
            chosen = targets if every else [rng.choice(targets)]
            seed = rng.random()  # every message of the kind gets the same change
            for i in chosen:
                m = msgs[i]
                p = _PB[kind]()
                p.ParseFromString(m.payload)
                desc = mutate_proto(random.Random(seed), p)
                msgs[i] = Message(m.key, p.SerializeToString(), m.log_time_ns, m.seq)
            what.append(f"{'every' if every else 'one'} {kind}: {desc}")
        elif op < 0.65:
            i = rng.choice(idx)
            del msgs[i]
            what.append(f"drop message {i}")
        elif op < 0.75:
            i = rng.choice(idx)
            m = msgs[i]
            msgs.insert(i + rng.randint(0, 30), Message(m.key, m.payload, m.log_time_ns, m.seq + rng.choice([0, 1])))
            what.append(f"duplicate message {i}")
        elif op < 0.83:
            i = rng.choice(idx)
            j = min(len(msgs), i + rng.randint(2, 60))
            part = msgs[i:j]
            rng.shuffle(part)
            msgs[i:j] = part
            what.append(f"shuffle messages {i}-{j}")
        elif op < 0.91:
            i = rng.choice(idx)
            m = msgs[i]
            msgs[i] = Message(m.key, m.payload, m.log_time_ns, rng.choice([0, 2**32 - 1, 2**31, m.seq + 1000]))
            what.append(f"message {i} seq {msgs[i].seq}")
        else:  # a payload on another key
            i, j = rng.choice(idx), rng.randrange(len(msgs))
            msgs[i] = Message(msgs[i].key, msgs[j].payload, msgs[i].log_time_ns, msgs[i].seq)
            what.append(f"payload of message {j} on {msgs[i].key}")
    return msgs, "; ".join(what)


def _write(path: Path, messages: list[Message]) -> None:
    with McapRecorder(path) as rec:
        for m in messages:
            rec.write(m.key, m.payload, m.log_time_ns, seq=m.seq)


def test_fuzz_mcap_content(workdir, base_mcap, processed_mcap):
    rng = random.Random(SEED + 3)
    raw = read_recording(base_mcap).messages
    processed = read_recording(processed_mcap).messages
    outcomes = []
    t0 = time.perf_counter()
    for i in range(N_MCAP_CONTENT):
        path = workdir / f"c{i}.mcap"
        msgs, what = forge(rng, raw, ("meta", "opr", "toa", "truth"))
        _write(path, msgs)
        outcomes.append(run_case(f"mcap content #{i} ({what})", ["process", path]))
    for i in range(N_VIEW):  # the views: raw recordings (processed first) and forged processor output
        path = workdir / f"v{i}.mcap"
        if i % 2:
            msgs, what = forge(rng, processed, ("fit", "tw", "resonance", "meta"))
        else:
            msgs, what = forge(rng, raw, ("meta", "opr", "toa", "truth"))
        _write(path, msgs)
        outcomes.append(run_case(f"view #{i} ({what})", ["view", path, "--rrd", path.with_suffix(".rrd")]))
    tally = _tally(outcomes)
    print(f"mcap content: {len(outcomes)} cases, statuses {tally}, {time.perf_counter() - t0:.1f} s")
    assert not any(o.problem for o in outcomes), report(outcomes)


def _extremes(f) -> list:
    """The ends of a field's type: int64 / int32 / uint64 / uint32 limits, NaN, +-inf, +-1e308."""
    if f.type in (f.TYPE_DOUBLE, f.TYPE_FLOAT):
        return [math.nan, math.inf, -math.inf, 1e308, -1e308, -0.0, 5e-324]
    if f.type in (f.TYPE_INT64, f.TYPE_SINT64, f.TYPE_SFIXED64):
        return [-(2**63), 2**63 - 1]
    if f.type in (f.TYPE_INT32, f.TYPE_SINT32, f.TYPE_SFIXED32):
        return [-(2**31), 2**31 - 1]
    if f.type in (f.TYPE_UINT64, f.TYPE_FIXED64):
        return [2**64 - 1, 2**63]
    if f.type in (f.TYPE_UINT32, f.TYPE_FIXED32):
        return [2**32 - 1, 2**31]
    return []


def _number_paths(desc, prefix: tuple = ()):
    """Paths (field names) of every number of a message type, through nested messages."""
    for f in desc.fields:
        if f.type == f.TYPE_MESSAGE:
            yield from _number_paths(f.message_type, prefix + (f.name,))
        elif _extremes(f):
            yield prefix + (f.name,)


def _set_extreme(msg, path: tuple, value, rng: random.Random) -> bool:
    """Set the number at ``path`` of ``msg`` (one element of a repeated field, one item of a
    repeated message) to ``value``, in place; False when the message has no such number."""
    f = msg.DESCRIPTOR.fields_by_name[path[0]]
    if len(path) > 1:
        if codec.is_repeated(f):
            items = getattr(msg, f.name)
            return bool(len(items)) and _set_extreme(items[rng.randrange(len(items))], path[1:], value, rng)
        return _set_extreme(getattr(msg, f.name), path[1:], value, rng)
    if codec.is_repeated(f):
        items = getattr(msg, f.name)
        if not len(items):
            return False
        items[rng.randrange(len(items))] = value
    else:
        setattr(msg, f.name, value)
    return True


def forge_extreme(rng: random.Random, messages: list[Message], kinds) -> tuple[list[Message], str]:
    """Messages with one number of one message kind (in one message, or in every message of the
    kind) set to an extreme of its type: a well-formed recording with absurd values."""
    present = sorted({keys.parse_key(m.key).kind for m in messages} & set(kinds))
    kind = rng.choice(present)
    paths = list(_number_paths(_PB[kind].DESCRIPTOR))
    path = rng.choice(paths)
    f = _PB[kind].DESCRIPTOR
    for name in path[:-1]:
        f = f.fields_by_name[name].message_type
    value = rng.choice(_extremes(f.fields_by_name[path[-1]]))
    targets = [i for i, m in enumerate(messages) if keys.parse_key(m.key).kind == kind]
    every = rng.random() < 0.3
    chosen = set(targets if every else [rng.choice(targets)])
    out, changed = [], 0
    for i, m in enumerate(messages):
        if i in chosen:
            p = _PB[kind]()
            p.ParseFromString(m.payload)
            if _set_extreme(p, path, value, random.Random(rng.random())):
                changed += 1
                m = Message(m.key, p.SerializeToString(), m.log_time_ns, m.seq)
        out.append(m)
    return out, f"{'every' if every else 'one'} {kind}: {'.'.join(path)} = {value!r} ({changed} changed)"


def test_fuzz_extreme_values(workdir, base_mcap, processed_mcap):
    """Well-formed recordings whose numbers sit at the ends of their types (int64 min/max,
    uint64 max, NaN, +-inf, +-1e308), processed, viewed and exported: results, one-line
    errors (and nothing else on stderr), never a traceback or a hang."""
    rng = random.Random(SEED + 7)
    raw = read_recording(base_mcap).messages
    processed = read_recording(processed_mcap).messages
    outcomes = []
    t0 = time.perf_counter()
    for i in range(N_EXTREME):
        command = ("process", "view", "export")[i % 3]
        path = workdir / f"x{i}.mcap"
        if command == "process":
            msgs, what = forge_extreme(rng, raw, ("meta", "opr", "toa", "truth"))
        else:
            msgs, what = forge_extreme(rng, processed, tuple(_PB))
        _write(path, msgs)
        argv = {"process": ["process", path], "view": ["view", path, "--rrd", path.with_suffix(".rrd")],
                "export": ["export", path, "--format", "csv", "--out", workdir / f"x{i}"]}[command]
        o = run_case(f"extreme #{i} ({what})", argv)
        _one_line(o)
        outcomes.append(o)
    tally = _tally(outcomes)
    print(f"extreme values: {len(outcomes)} cases, statuses {tally}, {time.perf_counter() - t0:.1f} s")
    assert not any(o.problem for o in outcomes), report(outcomes)


@pytest.mark.parametrize("value", [-(2**63), 2**63 - 1, codec.MAX_REVOLUTIONS + 1], ids=["int64_min", "int64_max",
                                                                                         "above_limit"])
def test_issue_view_of_an_extreme_travelling_wave_revolution(workdir, processed_mcap, value):
    """The issue: one TravellingWave at revolution -2^63 made ``bttsim view`` raise ValueError."""
    msgs = read_recording(processed_mcap).messages
    i = next(k for k, m in enumerate(msgs) if keys.parse_key(m.key).kind == "tw")
    p = pb.TravellingWave.FromString(msgs[i].payload)
    p.header.revolution = value
    msgs[i] = Message(msgs[i].key, p.SerializeToString(), msgs[i].log_time_ns, msgs[i].seq)
    path = workdir / f"tw-rev-{value}.mcap"
    _write(path, msgs)
    o = run_case("tw revolution", ["view", path, "--rrd", path.with_suffix(".rrd")])
    _one_line(o)
    assert o.problem is None and o.status == 2 and "header revolution" in o.err, report([o]) if o.problem else o.err


def test_fuzz_signal_and_double_pulse_content(workdir):
    """Forged raw-signal windows (``SignalBatch``) and TOA batches carrying double pulses
    (``extra_toa_s`` / ``extra_toa_ticks``), processed and viewed: one-line errors, warnings
    or results, never a traceback or a hang."""
    toml = workdir / "signal.toml"
    toml.write_text(SIGNAL_TOML)
    base = workdir / "signal.mcap"
    o = run_case("signal base", ["simulate", toml, "--out", base, "-q"])
    assert o.status == 0 and not o.problem, o.err
    raw = read_recording(base).messages
    kinds = {keys.parse_key(m.key).kind for m in raw}
    extra = sum(len(pb.ToaBatch.FromString(m.payload).extra_toa_s) for m in raw if "/toa/" in m.key)
    assert "signal" in kinds and extra > 0  # the fields under test are there to forge
    rng = random.Random(SEED + 5)
    outcomes = []
    for i in range(N_SIGNAL):
        path = workdir / f"s{i}.mcap"
        msgs, what = forge(rng, raw, ("signal", "toa"))
        _write(path, msgs)
        argv = ["process", path] if i % 2 else ["view", path, "--rrd", path.with_suffix(".rrd")]
        outcomes.append(run_case(f"signal #{i} ({what})", argv))
    print(f"signal content: {len(outcomes)} cases, statuses {_tally(outcomes)}")
    assert not any(o.problem for o in outcomes), report(outcomes)


# --------------------------------------------------------------------------------------
# A few through a real process: the exit status and stderr a shell sees
# --------------------------------------------------------------------------------------


def test_fuzz_sample_in_subprocesses(workdir, base_mcap, processed_mcap, frd_text):
    rng = random.Random(SEED + 4)
    bad_toml = workdir / "sub.toml"
    bad_toml.write_text("[[excitation]]\nengine_order = 4294967296\n")
    big_force = workdir / "force.toml"
    big_force.write_text(BASE_TOML + "[[excitation]]\namplitude_n = 1e6\n")
    cut = workdir / "sub.mcap"
    cut.write_bytes(mutate_bytes(rng, base_mcap.read_bytes())[0])
    forged = workdir / "sub_forged.mcap"
    _write(forged, forge(rng, read_recording(base_mcap).messages, ("meta", "opr", "toa"))[0])
    frd = workdir / "sub.frd"
    rows = frd_text.splitlines()
    i = next(k for k, ln in enumerate(rows) if ln.startswith(" -1"))
    rows[i] = _frd_field(rows[i], 25, 12, rows[i][25:37].replace("0", "O", 1))  # a letter O for a zero
    frd.write_text("\n".join(rows) + "\n")
    cases = [["scenario", "--check", bad_toml], ["simulate", big_force, "--out", workdir / "x.mcap"],
             ["process", cut], ["process", forged],
             ["model", "import", frd, *FRD_ARGS, "--out", workdir / "sub.npz"]]
    extreme = workdir / "sub_extreme.mcap"  # the view's log records would show here, not in-process
    _write(extreme, forge_extreme(rng, read_recording(processed_mcap).messages, ("tw",))[0])
    cases = (cases + [["view", extreme, "--rrd", extreme.with_suffix(".rrd")]])[:N_SUBPROCESS]
    for argv in cases:
        p = subprocess.run([sys.executable, "-m", "bttsim_stream.cli", *map(str, argv)], capture_output=True,
                           text=True, timeout=120)
        o = Outcome(f"subprocess {argv[0]}", argv, p.returncode, p.stdout, p.stderr)
        o.problem = judge(o)
        _one_line(o)
        assert o.problem is None, report([o])


# --------------------------------------------------------------------------------------
# The issue's own reproductions, by name
# --------------------------------------------------------------------------------------


def _edit(messages: list[Message], kind: str, change) -> list[Message]:
    """Messages with ``change(protobuf, header_revolution)`` applied to every message of ``kind``."""
    out = []
    for m in messages:
        if keys.parse_key(m.key).kind == kind:
            p = _PB[kind]()
            p.ParseFromString(m.payload)
            change(p, p.header.revolution)
            m = Message(m.key, p.SerializeToString(), m.log_time_ns, m.seq)
        out.append(m)
    return out


def _set_meta(**values):
    def change(p, _rev):
        for k, v in values.items():
            if isinstance(v, list):
                del getattr(p, k)[:]
                getattr(p, k).extend(v)
            else:
                setattr(p, k, v)
    return change


RECORDING_CASES = {
    "extra blade in the metadata": ("meta", _set_meta(n_blades=30, sensing_angles_rad=[], n_families=0,
                                                      family_freq_hz=[]), "30"),
    "wrong blade count in the TOA batches": ("toa", lambda p, r: p.toa_s.append(p.toa_s[-1] + 1e-4), "ignored"),
    "NaN OPR times": ("opr", lambda p, r: setattr(p, "opr_s", math.nan) if r % 7 == 3 else None, "missing"),
    "negative OPR times": ("opr", lambda p, r: setattr(p, "opr_s", -p.opr_s), "OPR times must increase"),
    "non-monotonic OPR times": ("opr", lambda p, r: setattr(p, "opr_s", p.opr_s - 0.5) if r % 5 == 4 else None,
                                "OPR times must increase"),
    "zero tip radius": ("meta", _set_meta(tip_radius_m=0.0), "tip_radius_m"),
    "huge probe angle": ("meta", _set_meta(probe_angles_rad=[1e10, 0.26, 0.41, 3.8, 5.2]), "probe_angles_rad"),
    "huge engine order": ("meta", _set_meta(engine_orders=[2**31]), "engine order"),
    "huge revolution count": ("meta", _set_meta(n_revolutions=2**62), "n_revolutions"),
    "infinite TOA": ("toa", lambda p, r: p.toa_s.__setitem__(3, math.inf), "TOA(s) not within a revolution"),
    "no revolutions in the metadata": ("meta", _set_meta(n_revolutions=0), "n_revolutions = 0"),
    "speed range upside down": ("meta", _set_meta(speed_min_rpm=5000.0), "the lowest above the highest"),
    "NaN metadata time": ("meta", lambda p, r: setattr(p.header, "t_s", math.nan), "header time nan"),
    "another run's metadata": ("meta", lambda p, r: (setattr(p, "run_id", "forged"),
                                                     setattr(p.header, "run_id", "forged")), "another run's id"),
}


@pytest.mark.parametrize("command", ["process", "view"])
@pytest.mark.parametrize("name", list(RECORDING_CASES))
def test_issue_recordings_give_one_line_errors(workdir, base_mcap, name, command):
    kind, change, words = RECORDING_CASES[name]
    path = workdir / f"issue-{command}-{name.replace(' ', '_')}.mcap"
    _write(path, _edit(read_recording(base_mcap).messages, kind, change))
    argv = [command, path] + (["--rrd", path.with_suffix(".rrd")] if command == "view" else [])
    o = run_case(name, argv)
    assert o.problem is None and o.status == 2, report([o]) if o.problem else o.err
    assert words in o.err, o.err


def _with_copy_before(messages: list[Message], kind: str, revolution: int, change) -> list[Message]:
    """Messages with a changed copy of the first ``kind`` message of ``revolution`` (or the
    metadata) placed right before it, with its key and number (a forger who comes first)."""
    out, done = [], False
    for m in messages:
        if not done and keys.parse_key(m.key).kind == kind and (kind == "meta" or m.seq == revolution):
            p = _PB[kind]()
            p.ParseFromString(m.payload)
            change(p)
            out.append(Message(m.key, p.SerializeToString(), m.log_time_ns, m.seq))
            done = True
        out.append(m)
    assert done
    return out


def _without_probes(messages: list[Message], probes) -> list[Message]:
    def empty(p, _rev):
        if p.probe in probes:
            p.toa_s[:] = [math.nan] * len(p.toa_s)
    return _edit(messages, "toa", empty)


def test_probes_without_any_toa_leave_the_others_to_separate_the_orders(workdir, base_mcap):
    """Probes that hold no TOA in the whole recording: if the probes left cannot separate the
    engine order (or fit several jointly), ``process`` refuses, naming them (before: NaN fits
    reported as no resonance found, exit 0); if they can, a note names them. The recording's
    tables still export."""
    raw = read_recording(base_mcap).messages
    cases = [((2, 3, 4), [], 2, "probe(s) 2, 3, 4 hold no TOA in the whole recording; the probe layout"),
             ((4,), ["--eo", "8,9"], 2, "the probes left cannot fit EO 8+9 jointly"),
             ((0, 1, 2, 3, 4), [], 2, "no probe holds a TOA")]
    for probes, options, status, words in cases:
        path = workdir / f"empty-{'-'.join(map(str, probes))}{'-joint' if options else ''}.mcap"
        _write(path, _without_probes(raw, probes))
        o = run_case(f"probes {probes} without TOAs", ["process", path, *options])
        assert o.problem is None and o.status == status, report([o]) if o.problem else o.err
        assert words in (o.out if status == 0 else o.err), (o.out, o.err)
    o = run_case("export of it", ["export", path.with_name("empty-2-3-4.mcap"), "--out", workdir / "empty.export"])
    assert o.problem is None and o.status == 0, o.err
    # one empty probe of five: the others separate EO 8, and the note says which is empty
    from bttsim_stream.offline import check_probes, load_run
    from bttsim_stream.process.options import ProcessOptions

    _write(workdir / "empty-4.mcap", _without_probes(raw, (4,)))
    assert check_probes("f", load_run(workdir / "empty-4.mcap"), ProcessOptions()) == [
        "probe(s) 4 hold no TOA in the whole recording: the others are fitted"]
    assert check_probes("f", load_run(base_mcap), ProcessOptions()) == []


@pytest.mark.parametrize("command", ["process", "export"])
def test_a_second_different_message_for_a_number_is_refused(workdir, base_mcap, command):
    """A recorder writes the first payload of a number and refuses the others; a recording
    holding two different ones (a forger's before the real one) cannot say which is the
    acquisition (or the truth): one line, status 2. The same message twice is a duplicate, counted."""
    raw = read_recording(base_mcap).messages

    def shifted(p):
        p.toa_s[:] = [t + 1e-6 for t in p.toa_s]

    cases = {
        "toa": (_with_copy_before(raw, "toa", 5, shifted), "differ from an earlier one of the same revolution"),
        "opr": (_with_copy_before(raw, "opr", 7, lambda p: setattr(p, "opr_s", p.opr_s + 1e-6)),
                "the OPR pulse of revolution 7"),
        "meta": (_with_copy_before(raw, "meta", 0, lambda p: setattr(p, "tip_radius_m", 0.5)),
                 "a second, different run metadata"),
        "truth": (_with_copy_before(raw, "truth", 9, lambda p: p.d_eqv_pkpk_m.__setitem__(0, 2 * p.d_eqv_pkpk_m[0])),
                  "1 truth message(s) differ from an earlier one of the same revolution (first: revolution 9)"),
        "same": (_with_copy_before(raw, "toa", 5, lambda p: None), None),
    }
    for name, (msgs, words) in cases.items():
        path = workdir / f"second-{command}-{name}.mcap"
        _write(path, msgs)
        argv = [command, path] + (["--out", workdir / f"second-{name}.export"] if command == "export" else [])
        o = run_case(f"a second {name} message", argv)
        assert o.problem is None, report([o])
        if words is None:
            assert o.status == 0, o.err
        else:
            assert o.status == 2 and words in o.err, o.err


SCENARIO_CASES = {
    "engine_order = 4294967296": ("[[excitation]]\nengine_order = 4294967296\n", "engine_order"),
    "1 blade": ("[rotor]\nn_blades = 1\n[[excitation]]\nnodal_diameter = 0\n", "n_blades"),
    "1000 blades": ("[rotor]\nn_blades = 1000\n", "n_blades must be an integer in [2, 200]"),
    "1 probe": ("[probes]\nangles_deg = [5.0]\n", "cannot separate"),
    "amplitude_n = 1e300": ("[[excitation]]\namplitude_n = 1e300\n", "above 5% of the tip radius"),
    "amplitude_n = 1e6": ("[[excitation]]\namplitude_n = 1e6\n", "above 5% of the tip radius"),
    "a year-long run": ("[speed]\nduration_s = 3.2e7\n", "revolutions"),
    "a run of no revolution": ("[speed]\nstart_rpm = 0.001\nend_rpm = 0.002\nduration_s = 6.0\n",
                               "no whole revolution"),
    "a probe off the tip": ("[probes]\naxial_position_m = 0.005\n", "lies outside the model's tip nodes"),
}


@pytest.mark.parametrize("name", list(SCENARIO_CASES))
def test_issue_scenarios_are_refused_by_the_check(workdir, name):
    text, words = SCENARIO_CASES[name]
    path = workdir / f"issue-{name.replace(' ', '_').replace('=', '')}.toml"
    path.write_text(BASE_TOML + text if not text.startswith("[speed]") else text)
    o = run_case(name, ["scenario", "--check", path])
    assert o.problem is None and o.status == 2 and words in o.err, report([o]) if o.problem else o.err
    o = run_case(name, ["simulate", path, "--out", path.with_suffix(".mcap"), "-q"])
    if o.status == 0:  # an acquisition the simulator can make (1 probe): its processing is refused
        o = run_case(name, ["process", path.with_suffix(".mcap")])
    assert o.problem is None and o.status == 2 and words in o.err, report([o]) if o.problem else o.err


def test_issue_model_without_blade_alone_frequencies(workdir):
    path = workdir / "no-blade-alone.npz"
    model = build_model(Scenario())
    arrays = {k: v for k, v in model.as_arrays().items()}
    arrays["blade_alone_freq_hz"] = np.zeros(0)
    _save(path, arrays)
    o = run_case("empty blade_alone_freq_hz", ["model", "show", path, "--png", workdir / "x.png"])
    assert o.problem is None and o.status == 2 and "blade_alone_freq_hz" in o.err, o.err


# --------------------------------------------------------------------------------------
# The recorder's gate: every bus message untrusted
# --------------------------------------------------------------------------------------

N_GATE = 3000


def test_fuzz_recorder_gate(processed_mcap):
    """Mutated payloads (mutate_bytes), wrong keys, numbers and times, other sessions: the
    recorder's gate never raises, never writes a message that does not decode or that is not
    its run's, and keeps writing the real stream whole (``missing`` stays empty)."""
    from bttsim_stream.bus.admission import RecordGate

    rng = random.Random(SEED + 9)
    real = read_recording(processed_mcap).messages
    meta = next(m for m in real if m.key.endswith("/meta"))
    run_id = codec.decode_run_metadata(meta.payload, meta.key).body.run_id
    gate = RecordGate("rig1")
    written = {}
    keyset = sorted({m.key for m in real}) + ["bttsim/rig1/toa/99", "bttsim/rig2/opr", "bttsim/rig1/status/sim",
                                             "bttsim/rig1", "other/key", "bttsim/rig1/toa/x"]
    forged = []
    for _ in range(N_GATE):
        m = real[rng.randrange(len(real))]
        payload, _ = mutate_bytes(rng, m.payload) if rng.random() < 0.8 else (m.payload, "as is")
        key = m.key if rng.random() < 0.7 else rng.choice(keyset)
        seq = rng.choice([m.seq, m.seq + 1, rng.randrange(-5, 1 << 20), 2**64 - 1, 0])
        t = rng.choice([m.log_time_ns, 0, -1, 2**63 - 1, rng.randrange(1 << 40)])
        att = None if rng.random() < 0.05 else (seq, t)
        forged.append((key, payload, att, rng.choice(["sim", "forger", None])))
    stream = [(m.key, m.payload, (m.seq, m.log_time_ns), "sim") for m in real]
    mixed = []
    for item in stream:  # the real stream in order, forgeries interleaved
        mixed.append(item)
        while forged and rng.random() < 0.6:
            mixed.append(forged.pop())
    mixed += forged
    whole = RecordGate("rig1", decode=True)  # a viewer's gate: decodes every message whole
    for key, payload, att, source in mixed:
        verdicts = gate.admit(key, payload, att, source)
        assert [_verdict(v) for v in verdicts] == [_verdict(v) for v in whole.admit(key, payload, att, source)]
        for v in verdicts:
            assert v.action in ("write", "duplicate", "reject"), v
            if v.action == "write":
                d = codec.decode_message(v.key, v.payload)
                assert d.header.run_id == run_id and d.header.seq == v.seq, v.key
                assert written.setdefault((v.key, v.seq), v.payload) == v.payload
    gate.finish()
    real_set = {(m.key, m.seq): m.payload for m in real}
    assert all(real_set.get(k) == p or k[0].rsplit("/", 1)[-1] not in ("opr", "truth", "meta") for k, p in
               written.items())
    assert gate.missing() == {} or all("/toa/" not in k and not k.endswith(("/opr", "/truth"))
                                       for k in gate.missing()), gate.missing()
    assert gate.rejected > N_GATE // 2, gate.summary()


def _verdict(v) -> tuple:
    return v.action, v.key, v.payload, v.seq, v.log_time_ns, v.reason, v.keep


N_CHECK = 4000


def test_fuzz_check_refuses_exactly_what_decode_refuses(processed_mcap):
    """``check_message`` (the recorder's check, bodies not built) against ``decode_message`` on
    hostile payloads of every message type: the same payloads refused, and for the others the
    same header, blade count and OPR time."""
    rng = random.Random(SEED + 10)
    real = read_recording(processed_mcap).messages
    kinds = sorted({keys.parse_key(m.key).kind for m in real})
    refused = 0
    for i in range(N_CHECK):
        m = real[rng.randrange(len(real))] if i % 2 else rng.choice(
            [x for x in real if keys.parse_key(x.key).kind == kinds[i // 2 % len(kinds)]])
        payload = _hostile_payload(rng, m)
        key = m.key if rng.random() < 0.9 else rng.choice(real).key
        try:
            whole = codec.Checked.of(codec.decode_message(key, payload))
        except BttsimError:
            whole = None
        try:
            checked = codec.check_message(key, payload)
        except BttsimError:
            checked = None
        assert (whole is None) == (checked is None), (key, payload[:80])
        if whole is None:
            refused += 1
            continue
        assert checked.header == whole.header or checked.header.t_s != checked.header.t_s
        assert (checked.n_blades, checked.opr_s) == (whole.n_blades, whole.opr_s) or \
            (checked.opr_s != checked.opr_s and whole.opr_s != whole.opr_s)
    assert N_CHECK // 10 < refused < N_CHECK - N_CHECK // 10  # both sides of the line were tried


def _hostile_payload(rng: random.Random, m) -> bytes:
    """A mutation of message ``m``'s payload: its bytes, or (half the time, for a kind with a
    protobuf class) a field of its parsed message."""
    kind = keys.parse_key(m.key).kind
    if rng.random() < 0.5 or kind not in _PB:
        return mutate_bytes(rng, m.payload)[0]
    p = _PB[kind]()
    p.ParseFromString(m.payload)
    mutate_proto(rng, p)
    return p.SerializeToString()


def test_fuzz_rows_refuse_exactly_what_decode_refuses(processed_mcap):
    """``opr_row``, ``toa_row`` and ``truth_row`` (how ``load_run`` reads) against the decoders
    on hostile payloads of the acquisition stream: the same error, word for word, and for the
    others the same values."""
    rng = random.Random(SEED + 11)
    real = [m for m in read_recording(processed_mcap).messages if keys.parse_key(m.key).kind in ("opr", "toa", "truth")]
    rows = {"opr": codec.opr_row, "toa": codec.toa_row, "truth": codec.truth_row}
    refused = 0
    for _ in range(N_CHECK):
        m = real[rng.randrange(len(real))]
        payload = _hostile_payload(rng, m)  # its kind is in _PB: the same draws as before
        key = m.key if rng.random() < 0.9 else rng.choice(real).key
        kind = keys.parse_key(key).kind
        try:
            whole, error = codec.decode_message(key, payload), None
        except BttsimError as exc:
            whole, error = None, str(exc)
        try:
            row, row_error = rows[kind](payload, key), None
        except BttsimError as exc:
            row, row_error = None, str(exc)
        assert error == row_error, (key, payload[:80])
        if whole is None:
            refused += 1
            continue
        assert row[:2] == (whole.header.run_id, whole.header.revolution)
        if kind == "opr":
            assert row[2] == whole.body.opr_s or row[2] != row[2]
        elif kind == "toa":
            assert row[2] == whole.body.probe and np.array_equal(row[3], whole.body.toa_s, equal_nan=True)
            assert np.array_equal(row[4], whole.body.extra_toa_s, equal_nan=True)
        else:
            for name, a in row[3].items():
                assert np.array_equal(a, getattr(whole.body, name), equal_nan=a.dtype.kind == "f"), name
    assert N_CHECK // 10 < refused < N_CHECK - N_CHECK // 10  # both sides of the line were tried
