"""Greedy view selection (METHOD.md stage 6) and its ablations.

The rule (paper): the kept set starts with every training view; feasible candidates are
visited by descending score f; a candidate is accepted when WIoU < 0.7 with every kept view;
stop after K = 500 accepted.

``nms_wiou`` gives exactly the result of that sequential rule but computes only what it needs,
in GEMM-sized blocks:

* candidates are visited in blocks of B (in score order); a block's WIoU against the kept
  set is one GEMM per kept group (training views, accepted candidates), and the block's own
  pairs one more small GEMM; the sequential decisions inside the block then only read these;
* exact pruning by scores: WIoU(i, j) <= min(f_i, f_j) / max(f_i, f_j), so a kept view can
  reach the threshold t only if its score lies in [t f_min, f_max / t] of the block. Training
  rows are sorted by f and accepted rows arrive in descending f, so both windows are
  contiguous slices;
* exact pruning by cell bounds (``Visibility`` cell summaries): L <= I <= U from two GEMMs
  over coarse cells (~3% of the voxels' cost). WIoU is increasing in I, so a pair with
  WIoU(L) >= t suppresses, and a pair with WIoU(U) < t cannot; only the undecided pairs of
  still-open candidates get the voxel-level product. Decisions keep a relative margin of
  1e-4 from t, so rounding cannot flip them.

Same inputs, same decisions as the plain rule (``nms_reference``), which the tests check.

Candidates with f <= min_score are never selected (``zero_score``); candidates not visited
because the budget was reached are ``budget``; the others are ``overlap`` (a kept view at or
above the threshold) or accepted.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from freescale_core.geometry.cameras import Cameras
from freescale_core.select.view_graph import pose_distance, wiou_from_inter
from freescale_core.select.visibility import Visibility

_REL_EPS = 1e-4  # bounds decide only when clear of the threshold by this relative margin

__all__ = ["NMSResult", "nms_wiou", "nms_pose_distance", "top_k_by_score", "nms_reference"]


@dataclass
class NMSResult:
    """Per-node outcome of the selection (nodes = training then candidates).

    Attributes:
        selected: ``[S]`` accepted candidate node ids, in acceptance order.
        status: ``[N]`` "train", "free_view", "suppressed" or "" (not a candidate given).
        reason: ``[N]`` for suppressed nodes: "overlap", "budget" or "zero_score"; else "".
        overlap: ``[N]`` max WIoU (or min pose distance) to the kept set at decision time:
            a certified lower bound of it (exact where a voxel-level product was needed);
            >= threshold exactly for overlap suppressions. NaN where not decided.
        stats: work counters (pairs decided by bounds, exact pairs, blocks).
    """

    selected: np.ndarray
    status: np.ndarray
    reason: np.ndarray
    overlap: np.ndarray
    stats: dict = field(default_factory=dict)


def _init(n_nodes: int, n_train: int):
    status = np.full(n_nodes, "", dtype="<U10")
    status[:n_train] = "train"
    return status, np.full(n_nodes, "", dtype="<U10"), np.full(n_nodes, np.nan)


def _split_zero(score, cand, min_score, status, reason):
    cand = np.asarray(cand, dtype=np.int64)
    zero = ~(score[cand] > min_score)
    status[cand[zero]] = "suppressed"
    reason[cand[zero]] = "zero_score"
    live = cand[~zero]
    return live[np.lexsort((live, -score[live]))]  # f descending, ties by node id


def nms_wiou(vis: Visibility, n_train: int, candidates: np.ndarray, threshold: float = 0.7,
             max_views: int = 500, min_score: float = 0.0, block_rows: int = 256,
             dtype=np.float32, kept: np.ndarray | None = None) -> NMSResult:
    """Stage 6 WIoU NMS, exact, blocked and pruned (see module docstring).

    Args:
        vis: visibility of all nodes (training views are nodes ``0 .. n_train-1``); its cell
            summaries (if any) enable the bounds.
        n_train: T.
        candidates: node ids of the feasible candidates.
        threshold: accept when WIoU < threshold with every kept view.
        max_views: K, accepted candidates at most.
        min_score: candidates with f <= this are never selected.
        block_rows: candidates per block.
        dtype: GEMM precision of the exact products.
        kept: further node ids in the kept set from the start (besides the training views),
            e.g. the views a first pass accepted when a relaxed pass draws the selection's
            reserve (``run_selection``); their status is left as given.
    """
    N = vis.n_views
    f = vis.score
    fn = f / vis.norm
    status, reason, overlap = _init(N, n_train)
    order = _split_zero(f, candidates, min_score, status, reason)
    bounds = vis.n_cells > 0
    hi_eps, lo_eps = threshold * (1 + _REL_EPS), threshold * (1 - _REL_EPS)
    # kept group 1: training views that see something, sorted by score (ascending)
    tr = np.arange(n_train)
    if kept is not None and len(kept):
        tr = np.concatenate([tr, np.asarray(kept, np.int64)])
    tr = tr[fn[tr] > 0]
    tr = tr[np.argsort(fn[tr], kind="stable")]
    f_tr = fn[tr]
    R0_tr, R1_tr = vis.bound_rows(tr, "right") if bounds else (None, None)
    # kept group 2: accepted candidates, in acceptance order (= descending score)
    cap = max(0, min(max_views, len(order)))
    acc_nodes = np.empty(cap, np.int64)
    f_acc = np.empty(cap)
    nc = vis.n_cells
    R0_acc = np.empty((cap, 2 * nc), np.float32)
    R1_acc = np.empty((cap, nc), np.float32)
    n_acc = 0
    selected: list[int] = []
    stats = {"bound_pairs": 0, "exact_pairs": 0, "exact_rows": 0, "blocks": 0}
    slack = 1.0 - 1e-6  # widen the score window against rounding
    pos = 0
    while pos < len(order) and n_acc < max_views:
        ids = order[pos:pos + block_rows]
        pos += len(ids)
        stats["blocks"] += 1
        B = len(ids)
        fb = fn[ids]
        lo_f, hi_f = threshold * fb.min() * slack, fb.max() / (threshold * slack)
        groups = []
        a, b = np.searchsorted(f_tr, lo_f, "left"), np.searchsorted(f_tr, hi_f, "right")
        if b > a:
            groups.append((tr[a:b], f_tr[a:b], (R0_tr[a:b], R1_tr[a:b]) if bounds else None))
        if n_acc:
            na = -f_acc[:n_acc]  # ascending
            a, b = np.searchsorted(na, -hi_f, "left"), np.searchsorted(na, -lo_f, "right")
            if b > a:
                groups.append((acc_nodes[a:b], f_acc[a:b],
                               (R0_acc[a:b], R1_acc[a:b]) if bounds else None))
        best = np.zeros(B)  # max WIoU to the kept set: certified lower bound, exact if computed
        undecided = []
        if bounds and groups:
            L0, L1 = vis.bound_rows(ids, "left")
        for nodes_g, f_g, rr in groups:
            if bounds:
                low = L0 @ rr[0].T
                up = low + L1 @ rr[1].T
                best = np.maximum(best, wiou_from_inter(low, fb, f_g).max(axis=1))
                und = (wiou_from_inter(up, fb, f_g) >= lo_eps)
                stats["bound_pairs"] += und.size
            else:
                und = np.ones((B, len(nodes_g)), bool)
            undecided.append((nodes_g, f_g, und))
        # exact products only for rows still open and the kept views they are unsure about
        open_rows = best < hi_eps
        need = np.zeros(B, bool)
        cols = []
        for nodes_g, _, und in undecided:
            und = und & open_rows[:, None]
            need |= und.any(axis=1)
            cols.append(nodes_g[und.any(axis=0)])
        cols = np.concatenate(cols) if cols else np.zeros(0, np.int64)
        if need.any() and len(cols):
            rows_n = np.flatnonzero(need)
            Ar = vis.weighted_rows(ids[rows_n], dtype)
            Ac = vis.weighted_rows(cols, dtype)
            we = wiou_from_inter(Ar @ Ac.T, fb[rows_n], fn[cols])
            best[rows_n] = np.maximum(best[rows_n], we.max(axis=1))
            stats["exact_pairs"] += we.size
            stats["exact_rows"] += len(rows_n)
        # sequential decisions inside the block (earlier accepted rows are kept views too)
        tent = np.flatnonzero(best < threshold)
        if len(tent) > 1:
            At = vis.weighted_rows(ids[tent], dtype)
            wb = wiou_from_inter(At @ At.T, fb[tent], fb[tent])
        tpos = {int(li): p for p, li in enumerate(tent)}
        acc_local: list[int] = []
        new_acc: list[int] = []
        for li, node in enumerate(ids):
            if n_acc >= max_views:
                status[ids[li:]] = "suppressed"
                reason[ids[li:]] = "budget"
                break
            mm = best[li]
            if mm < threshold and acc_local:
                mm = max(mm, float(wb[tpos[li], acc_local].max()))
            overlap[node] = mm
            if mm < threshold:
                status[node] = "free_view"
                selected.append(int(node))
                acc_nodes[n_acc] = node
                f_acc[n_acc] = fb[li]
                n_acc += 1
                acc_local.append(tpos[li])
                new_acc.append(int(node))
            else:
                status[node] = "suppressed"
                reason[node] = "overlap"
        if bounds and new_acc:
            r0, r1 = vis.bound_rows(np.array(new_acc), "right")
            R0_acc[n_acc - len(new_acc):n_acc] = r0
            R1_acc[n_acc - len(new_acc):n_acc] = r1
    rest = order[pos:]
    status[rest] = "suppressed"
    reason[rest] = "budget"
    return NMSResult(np.array(selected, np.int64), status, reason, overlap, stats)


def top_k_by_score(score: np.ndarray, n_train: int, candidates: np.ndarray,
                   max_views: int = 500, min_score: float = 0.0) -> NMSResult:
    """Ablation "no view graph": the K candidates with the highest score, no suppression."""
    N = score.shape[0]
    status, reason, overlap = _init(N, n_train)
    order = _split_zero(score, candidates, min_score, status, reason)
    sel = order[:max_views]
    status[sel] = "free_view"
    status[order[max_views:]] = "suppressed"
    reason[order[max_views:]] = "budget"
    return NMSResult(sel.astype(np.int64), status, reason, overlap)


def nms_pose_distance(cams: Cameras, n_train: int, candidates: np.ndarray, spacing: float,
                      rot_unit_deg: float = 10.0, threshold: float = 3.5,
                      max_views: int = 500, seed: int = 0) -> NMSResult:
    """Ablation "no certainty grid": greedy selection with pose distance instead of WIoU.

    Without a grid there is no score, so candidates are visited in a seeded random order; a
    candidate is accepted when its pose distance to every kept view is >= ``threshold``.
    ``overlap`` holds the minimum distance to the kept set at decision time.
    """
    N = len(cams)
    status, reason, overlap = _init(N, n_train)
    cand = np.asarray(candidates, dtype=np.int64)
    order = np.random.default_rng([int(seed), 3000]).permutation(cand)
    if len(order) == 0:
        return NMSResult(np.zeros(0, np.int64), status, reason, overlap)
    cc = cams.subset(order)
    mind = np.full(len(order), np.inf)
    if n_train:
        mind = pose_distance(cc, cams.subset(np.arange(n_train)), spacing, rot_unit_deg).min(axis=1)
    selected = []
    for p, node in enumerate(order):
        if len(selected) >= max_views:
            status[order[p:]] = "suppressed"
            reason[order[p:]] = "budget"
            break
        overlap[node] = mind[p]
        if mind[p] >= threshold:
            status[node] = "free_view"
            selected.append(int(node))
            if p + 1 < len(order):
                d = pose_distance(cc.subset([p]), cc.subset(np.arange(p + 1, len(order))),
                                  spacing, rot_unit_deg)[0]
                mind[p + 1:] = np.minimum(mind[p + 1:], d)
        else:
            status[node] = "suppressed"
            reason[node] = "overlap"
    return NMSResult(np.array(selected, np.int64), status, reason, overlap)


def nms_reference(wiou: np.ndarray, score: np.ndarray, n_train: int, candidates: np.ndarray,
                  threshold: float = 0.7, max_views: int = 500,
                  min_score: float = 0.0) -> NMSResult:
    """The paper's rule written plainly on a full ``[N, N]`` WIoU matrix (tests only)."""
    N = score.shape[0]
    status, reason, overlap = _init(N, n_train)
    order = _split_zero(score, candidates, min_score, status, reason)
    kept = list(range(n_train))
    selected: list[int] = []
    for p, c in enumerate(order):
        if len(selected) >= max_views:
            status[order[p:]] = "suppressed"
            reason[order[p:]] = "budget"
            break
        mm = max((wiou[c, k] for k in kept), default=0.0)
        overlap[c] = mm
        if mm < threshold:
            kept.append(int(c))
            selected.append(int(c))
            status[c] = "free_view"
        else:
            status[c] = "suppressed"
            reason[c] = "overlap"
    return NMSResult(np.array(selected, np.int64), status, reason, overlap)
