"""Quick checks of bttsim_stream.studies: the cheap studies write Markdown with numbers."""

import re

from bttsim_stream import studies
from bttsim_stream.bench_ref import study_bench

TINY = {"speed": {"start_rpm": 2578.0, "segments": [{"duration_s": 0.03, "end_rpm": 2578.7}]}}


def test_table3_cn_only_writes_markdown(tmp_path):
    d = studies.study_table3(tmp_path, simulate_layouts=False)
    text = (tmp_path / "table3.md").read_text()
    assert "| 5, 15.15, 23.82, 220, 301.5 | 1.43 | 1.4 |" in text
    assert d["n_layouts"] == 462
    assert round(d["cn_min"], 1) == 1.4 and round(d["cn_max"], 1) == 16.7
    assert all(round(r["cn"], 1) == r["paper_cn"] for r in d["rows"])


def test_tiny_bench_agrees_with_reference(tmp_path):
    d = study_bench(tmp_path, window=TINY, blades=(0,), probes=(0,), full=False, scripts=False)
    text = (tmp_path / "bench.md").read_text()
    assert re.search(r"max abs\(reference - ours\) \| \d\.\d\de-\d\d s", text)
    assert d["reference"]["toas"] >= 1
    assert d["reference"]["max_abs_toa_diff_s"] < 1e-9


def test_main_rejects_unknown_study():
    import pytest

    with pytest.raises(SystemExit):
        studies.main(["nope"])
