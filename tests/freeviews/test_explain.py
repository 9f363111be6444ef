"""empty_reason: which stage left a scene without free views, with numbers."""

from types import SimpleNamespace

from freescale_core.freeviews.explain import empty_reason


def test_all_infeasible():
    c = {"n_candidates": 2000, "n_feasible": 0, "n_infeasible_inside_structure": 1990,
         "n_infeasible_outside_box": 10}
    assert empty_reason(c) == ("0 free views: 2000 candidates, 2000 infeasible "
                               "(1990 inside_structure, 10 outside_box)")


def test_all_rejected_by_quality_counts_reasons():
    c = {"n_candidates": 240, "n_feasible": 231, "n_selected": 40}
    recs = [SimpleNamespace(fail_reasons="brisque")] * 38 + \
        [SimpleNamespace(fail_reasons="black")] * 2
    fv = SimpleNamespace(counts={"final": 0, "passed": 0}, records=recs)
    assert empty_reason(c, fv) == ("0 free views: 240 candidates, 231 feasible, 40 selected, "
                                   "40 rejected by quality (brisque 38, black 2)")


def test_nonempty_is_blank_and_nms_zero():
    fv = SimpleNamespace(counts={"final": 3, "passed": 3}, records=[])
    assert empty_reason({"n_candidates": 5, "n_feasible": 5, "n_selected": 3}, fv) == ""
    r = empty_reason({"n_candidates": 5, "n_feasible": 5, "n_selected": 0, "n_zero_score": 5})
    assert "0 selected by NMS (5 zero score" in r
