"""Condition number of B (Eq. 16) and the probe layout search (paper Table 3, Sec. 3.3.3)."""

import math

import numpy as np
import pytest

from bttsim_stream.process import condition_number, design_matrix, rank_layouts
from bttsim_stream.process.probes import PAPER_CANDIDATES_DEG, PAPER_TABLE3


@pytest.mark.parametrize("angles,paper", PAPER_TABLE3, ids=[f"CN{p}" for _, p in PAPER_TABLE3])
def test_table3(angles, paper):
    # the table prints one decimal (1.4, 2, 10, 16.7 are 1.43, 2.00, 9.99, 16.74): every row
    # agrees to that precision, i.e. 2 significant figures below 10 and 3 above
    cn = condition_number(8, angles)
    assert round(cn, 1) == paper
    assert cn == pytest.approx(np.linalg.cond(design_matrix(np.deg2rad(angles), 8)), rel=1e-12)


def test_default_layout_value():
    assert condition_number(8, [5, 15.15, 23.82, 220, 301.5]) == pytest.approx(1.4328125, abs=1e-7)


def test_layout_search_of_the_paper():
    ranked = rank_layouts(8, PAPER_CANDIDATES_DEG, 5)
    assert len(ranked) == math.comb(11, 5) == 462
    assert round(ranked[0].cn, 1) == 1.4 and round(ranked[-1].cn, 1) == 16.7
    assert ranked[0].probe_angles_deg == (5.0, 15.15, 23.82, 220.0, 301.5)  # Table 1: the best
    assert ranked[-1].probe_angles_deg == (5.0, 10.6, 15.15, 148.5, 190.35)
    cns = [c.cn for c in ranked]
    assert cns == sorted(cns)
    by_angles = {c.probe_angles_deg: c.cn for c in ranked}
    for angles, _paper in PAPER_TABLE3:
        assert by_angles[tuple(angles)] == pytest.approx(condition_number(8, angles), rel=1e-12)


def test_degenerate_layouts():
    assert condition_number(8, [5, 15, 25]) < math.inf
    assert condition_number(8, [5, 15]) == math.inf  # fewer probes than unknowns
    assert condition_number(8, [0, 45, 90, 135]) == math.inf  # EO 8 sees them all at one phase
    assert condition_number((8, 3), [5, 15.15, 23.82, 220, 301.5]) > 1.0
    ranked = rank_layouts(8, [0, 45, 90, 10, 20], 3)
    assert ranked[-1].cn == math.inf and len(ranked) == 10
