"""Quick checks of bttsim_stream.paper: the cheap studies write files whose numbers match the paper."""

import json
import re
import subprocess
import sys

import pytest

from bttsim_stream import cli
from bttsim_stream.errors import BttsimError
from bttsim_stream.paper import studies
from bttsim_stream.paper.bench_ref import BENCH_DIR, study_bench

TINY = {"speed": {"start_rpm": 2578.0, "segments": [{"duration_s": 0.03, "end_rpm": 2578.7}]}}

#: Table 3 of the paper, typed from the paper (not from the library's PAPER_TABLE3).
PAPER_TABLE3 = {
    "5, 15.15, 23.82, 220, 301.5": 1.4, "5, 23.82, 148.5, 220, 255.6": 1.5,
    "10.6, 15.15, 23.82, 190.35, 220": 2.0, "5, 23.82, 148.5, 190.35, 255.6": 2.6,
    "15.15, 148.5, 190.35, 202.11, 301.5": 3.8, "5, 10.6, 148.5, 220, 357": 5.0,
    "10.6, 148.5, 190.35, 255.6, 301.5": 7.3, "10.6, 15.15, 23.82, 148.5, 190.35": 10.0,
    "5, 10.6, 15.15, 148.5, 190.35": 16.7,
}


def _md_rows(text: str, first_header: str) -> list[list[str]]:
    """Body rows of the Markdown table whose first header cell is ``first_header``."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"| {first_header} |"))
    rows = []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip("|").split("|")])
    return rows


def _one_error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("bttsim: error:"), err
    return lines[0]


def test_table3_condition_numbers_in_the_markdown_match_the_paper(tmp_path):
    studies.study_table3(tmp_path, simulate_layouts=False)
    text = (tmp_path / "table3.md").read_text()
    rows = _md_rows(text, "probes (deg)")
    assert {r[0] for r in rows} == set(PAPER_TABLE3)
    for layout, cn_ours, cn_paper, *_ in rows:
        assert float(cn_paper) == PAPER_TABLE3[layout]
        assert abs(float(cn_ours) - PAPER_TABLE3[layout]) <= 0.05, layout  # the paper prints one decimal
    m = re.search(r"All (\d+) five-probe layouts of the 11 candidate angles: CN (\S+) \.\. (\S+) ", text)
    assert m and int(m[1]) == 462
    assert abs(float(m[2]) - 1.4) <= 0.05 and abs(float(m[3]) - 16.7) <= 0.05
    data = json.loads((tmp_path / "table3.json").read_text())
    assert [round(r["cn"], 1) for r in data["rows"]] == list(PAPER_TABLE3.values())


def test_nd_study_markdown_against_the_paper_and_figures(tmp_path):
    """ND 1 vs ND 14 (two default run-ups, ~8 s alone; cached when the pipeline tests ran)."""
    studies.study_nd(tmp_path)
    rows = {r[0]: r[1:] for r in _md_rows((tmp_path / "nd.md").read_text(), "quantity")}

    def pct(key):
        return float(rows[key][0].rstrip(" %"))

    assert rows["identified ND"] == ["1 / 14", "1 / 14"]
    btt = pct("mean frequency difference ND 14 vs ND 1, BTT")
    assert abs(btt - 0.99) < 0.1  # paper 0.99 %
    assert abs(btt - pct("mean frequency difference, d_eqv truth")) < 0.02
    assert abs(pct("natural-frequency difference of the family-1 mode pairs (model)") - 1.05) < 0.01
    # the amplitude split is the model's (documented: ~16 % vs the paper's 11.6 %); BTT must match the truth
    amp = pct("mean amplitude difference (A_ND1 - A_ND14) / A_ND14, BTT")
    assert 10 < amp < 20 and abs(amp - pct("mean amplitude difference, d_eqv truth")) < 0.1
    for png in ("fig12_nd_freq.png", "fig13_nd_amp.png"):
        data = (tmp_path / png).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000, png
    assert json.loads((tmp_path / "nd.json").read_text())["nd14"]["identified_nd"] == 14


def test_tiny_bench_agrees_with_reference_and_reports_missing_scripts(tmp_path):
    out = tmp_path / "out"
    study_bench(out, window=TINY, blades=(0,), probes=(0,), full=False, bench_dir=tmp_path / "no-bench")
    text = (out / "bench.md").read_text()
    m = re.search(r"max abs\(reference - ours\) \| (\d\.\d\de-\d\d) s", text)
    assert m and float(m[1]) < 1e-9
    data = json.loads((out / "bench.json").read_text())
    assert data["reference"]["toas"] >= 1 and data["reference"]["max_abs_toa_diff_s"] < 1e-9
    # an installed wheel has no bench/ folder: bench.md says so instead of failing
    for name in ("bench_process.py", "bench_model.py"):
        assert re.search(rf"\| `python bench/{name}` \| not run: no bench/ folder at .*no-bench", text), name
    assert set(data["scripts_not_run"]) == {"bench_process.py", "bench_model.py"}


def test_bench_scripts_are_found_from_the_package_not_the_working_directory():
    assert BENCH_DIR.is_absolute()
    assert (BENCH_DIR / "bench_process.py").is_file() and (BENCH_DIR / "bench_model.py").is_file()


def test_cli_rejects_unknown_study_in_one_line(tmp_path, capsys):
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exc:
        cli.main(["study", "nope", "--out", str(out)])
    assert exc.value.code == 2
    assert "nope" in _one_error_line(capsys.readouterr().err)
    assert not out.exists()
    with pytest.raises(BttsimError, match="unknown study 'nope'"):
        studies.run("nope", out)


def test_cli_study_needs_out(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["study", "table3"])
    assert exc.value.code == 2
    assert "--out" in _one_error_line(capsys.readouterr().err)


def test_cli_study_names_are_the_studies():
    sub = next(a for a in cli.build_parser()._actions if a.dest == "command")
    name = next(a for a in sub.choices["study"]._actions if a.dest == "name")
    assert list(name.choices) == [*studies.STUDIES, "all"]


def test_study_without_matplotlib_fails_in_one_line_before_simulating(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    assert cli.main(["study", "table2", "--out", str(tmp_path / "out")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert line == "bttsim: error: drawing the study figures needs matplotlib: pip install 'bttsim-stream[plot]'"
    assert not (tmp_path / "out").exists()


def test_module_entry_point_needs_out_and_writes_only_there(tmp_path, capsys, monkeypatch):
    with pytest.raises(SystemExit) as exc:
        studies.main(["table3"])
    assert exc.value.code == 2 and "--out" in capsys.readouterr().err
    # the CN-only table 3 stands in for the (50 s) full study: main -> run -> the study -> files
    monkeypatch.setitem(studies.STUDIES, "table3", lambda out: studies.study_table3(out, simulate_layouts=False))
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    out = tmp_path / "deep" / "out"
    assert studies.main(["table3", "--out", str(out)]) == 0
    assert (out / "table3.md").stat().st_size > 0 and (out / "table3.json").stat().st_size > 0
    assert list(cwd.iterdir()) == []
    assert f"table3: wrote {out / 'table3.md'}" in capsys.readouterr().err


def test_runtime_never_imports_the_paper():
    code = ("import sys, bttsim_stream.process, bttsim_stream.sim.core, bttsim_stream.model.report, "
            "bttsim_stream.cli, bttsim_stream.views; bttsim_stream.cli.build_parser(); "
            "print(sorted(m for m in sys.modules if m.startswith('bttsim_stream.paper') or m == 'matplotlib'))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "[]"
