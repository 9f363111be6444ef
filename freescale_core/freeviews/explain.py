"""Why a scene ended with no free views, in one line with the numbers of every stage.

A scene with 0 free views is still a complete, published version (its ``freeviews/`` arrays
are empty); its manifest row has ``status = ok``, ``n_free_views = 0`` and a non-empty
``empty_reason`` naming the stage that removed the candidates, e.g.::

    0 free views: 2000 candidates, 2000 infeasible (1990 inside_structure, 10 outside_box)
    0 free views: 240 candidates, 231 feasible, 40 selected, 40 rejected by quality (brisque 38, black 2)
"""

from __future__ import annotations

from collections import Counter

__all__ = ["empty_reason"]


def empty_reason(sel_counts: dict, fv=None) -> str:
    """One line saying which stage left the scene without free views ("" when it has some).

    Args:
        sel_counts: ``SelectionResult.counts`` (``n_candidates``, ``n_feasible``, ...).
        fv: the ``FreeViewResult`` (None when the free-view stage did not run).
    """
    nc = int(sel_counts.get("n_candidates", 0))
    if fv is not None and int(fv.counts.get("final", 0)) > 0:
        return ""
    head = "0 free views: "
    if nc == 0:
        return head + "0 candidates generated (no trajectory produced a camera)"
    nf = int(sel_counts.get("n_feasible", 0))
    if nf == 0:
        return head + (f"{nc} candidates, {nc} infeasible "
                       f"({int(sel_counts.get('n_infeasible_inside_structure', 0))} "
                       f"inside_structure, {int(sel_counts.get('n_infeasible_outside_box', 0))}"
                       " outside_box)")
    ns = int(sel_counts.get("n_selected", 0))
    s = f"{nc} candidates, {nf} feasible"
    if ns == 0:
        return head + (f"{s}, 0 selected by NMS ({int(sel_counts.get('n_zero_score', 0))} "
                       f"zero score, {int(sel_counts.get('n_suppressed_overlap', 0))} overlap,"
                       f" {int(sel_counts.get('n_suppressed_budget', 0))} budget)")
    s += f", {ns} selected"
    if fv is None:
        return head + f"{s}, free-view stage did not run"
    passed = int(fv.counts.get("passed", 0))
    if passed == 0:
        why = Counter(r for rec in fv.records for r in (rec.fail_reasons or "").split(",") if r)
        detail = ", ".join(f"{k} {v}" for k, v in sorted(why.items(), key=lambda kv: -kv[1]))
        return head + f"{s}, {ns} rejected by quality ({detail or 'no reason recorded'})"
    return head + f"{s}, {passed} passed quality, 0 kept by the final selection"
