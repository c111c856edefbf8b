"""Tests for the study-only pieces of tools/sfm_mixture_study.py (its selection rule and table; the fit's
pieces are tested in tests/test_sfm_mixture.py, the study itself needs the CAD renders)."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import sfm_mixture_study as mix  # noqa: E402


def _entry(sse):
    return {str(k): {"chosen": "x", "candidates": [{"init": "x", "sse_px2": v, "sfm": 1.0 + k, "refined": 2.0 + k}]}
            for k, v in sse.items()}


@pytest.mark.parametrize("sse, expected", [({1: 100.0, 2: 60.0, 3: 30.0}, 3),  # 40% then 50%
                                           ({1: 100.0, 2: 60.0, 3: 50.0}, 2),  # 40% then 17%
                                           ({1: 100.0, 2: 80.0, 3: 10.0}, 1),  # 20%: stop at once
                                           ({1: 100.0, 2: 50.0, 3: 70.0}, 2)])  # k=3 worse than k=2
def test_rule_accepts_one_more_group_per_clear_cut(sse, expected):
    k, chosen = mix.pick(_entry(sse), 0.3)
    assert k == expected and chosen[k]["sse_px2"] == sse[k]
    assert f"| {expected} |" in mix.table({"c": _entry(sse)}, 0.3)


def test_rule_with_frame_agreement_skips_disagreeing_splits():
    entry = {"1": {"chosen": "single", "candidates": [{"init": "single", "sse_px2": 100.0, "sfm": 1, "refined": 1}]},
             "2": {"chosen": "a", "candidates": [
                 {"init": "a", "sse_px2": 40.0, "frame_agreement_deg": 120.0, "sfm": 2, "refined": 2},
                 {"init": "b", "sse_px2": 50.0, "frame_agreement_deg": 20.0, "sfm": 3, "refined": 3}]},
             "3": {"chosen": "a", "candidates": [
                 {"init": "a", "sse_px2": 10.0, "frame_agreement_deg": 90.0, "sfm": 4, "refined": 4}]}}
    k, chosen = mix.pick(entry, 0.3)
    assert k == 3 and chosen[2]["init"] == "a"  # without the check: the lowest residual
    k, chosen = mix.pick(entry, 0.3, agreement=60.0)
    assert k == 2 and chosen[2]["init"] == "b" and 3 not in chosen  # the agreeing split only
    assert "frames within 60 deg" in mix.table({"c": entry}, 0.3, 60.0)


