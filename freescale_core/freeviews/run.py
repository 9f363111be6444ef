"""The ``freeviews`` stage: render, quality filter, pose rectification, final selection, image
rectification (METHOD.md stages 7-10), as one pure function, and its entry point
``run_free_view_stage`` (the selection's candidates, the reconstruction's renderer and the
reference rule's overlap function built from the stage's inputs; ``tasks/`` wraps it).

``run_freeviews`` takes the selected candidates and a *render function* (the 3DGS rasterizer
in the pipeline, a ray caster in tests, the sample scene's oracle in benchmarks):

    render_fn(world_from_cam [4, 4], fx, fy, cx, cy, width, height)
        -> (rgb float32 [H, W, 3] in [0, 1], depth float32 [H, W] camera z, alpha float32 [H, W])

Order of work per selected candidate ``j`` (node ``T + j`` of the view graph):

1. render at its pose, score (stage 7); pass -> kept;
2. fail -> pose rectification toward the nearest training camera, steps in order, each
   re-rendered and re-scored; the first pass wins (stage 8); none passes -> rejected;
3. the passing views go through the stepwise BRISQUE selection (stage 9);
4. each final view gets a reference training view (graph or pose rule; the graph rule uses the
   WIoU at the view's *final* pose when ``overlap_fn`` is given) and is rectified by the
   configured backend (stage 10). The scores that decided stages 7-9 are those of the render;
   ``brisque_rectified`` is the BRISQUE of the stored (rectified) image.

Deterministic: no randomness is used (``seed`` is recorded and passed to nothing yet); the
same inputs give the same table and images.
"""

from __future__ import annotations

import math
import time
import warnings
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from schemas.freeview import FinalSelectConfig, FreeViewConfig

from freescale_core.geometry.cameras import Cameras
from freescale_core.errors import ShapeError
from freescale_core.freeviews.quality import (QualityScores, black_ratio, brisque_score,
                                              depth_validity, failure_reasons, to_uint8)
from freescale_core.freeviews.rectify_image import (NoneRectifier, RectifierUnavailable, RenderedView, make_rectifier)
from freescale_core.freeviews.rectify_pose import nearest_training_camera, rectification_poses
from freescale_core.freeviews.references import ViewGraph, pose_distances, select_reference
from freescale_core.freeviews.trust import TrustContext, TrustScores
from freescale_core.scene.gaussians import Gaussians
from freescale_core.scene.images import psnr_u8
from freescale_core.scene.oracle import ground_truth_oracle
from freescale_core.scene.scene import Scene

__all__ = ["RenderFn", "FreeViewRecord", "FreeViewResult", "StageTimer", "final_selection",
           "final_selection_trust", "run_freeviews", "make_render_fn", "make_overlap_fn",
           "run_free_view_stage"]

RenderFn = Callable[..., tuple[np.ndarray, np.ndarray, np.ndarray]]


@dataclass(kw_only=True)
class FreeViewRecord(TrustScores):
    """One row of the per-view table (one selected candidate).

    Attributes:
        candidate: index into the candidate cameras.
        node: view-graph node id (``T + candidate``).
        world_from_cam: ``[4, 4]`` final pose (after pose rectification, if any).
        fx, fy, cx, cy, width, height: intrinsics of the stored image.
        brisque, black_ratio, depth_validity: stage-7 scores of the render at the final pose.
        passed: passed the quality filter (first try or after pose rectification).
        passed_first: passed at the original pose.
        fail_reasons: tests failed at the original pose (``"black,brisque,depth"`` subset).
        n_rect_steps: pose-rectification renders tried (0..len(steps)).
        rect_step: the step that passed (config unit), NaN when none.
        final: kept by the final selection (stage 9).
        reference_view: training index used by the image rectifier, -1 when none.
        reference_rule: ``wiou_direct``, ``graph_direct``, ``graph_2hop``, ``pose``,
            ``pose_fallback`` or "".
        reference_score: WIoU / path score / pose distance of the reference choice.
        rectifier: backend that produced the stored image ("" when not final).
        rect_weight: mean reference weight of the rectified image (0 = pure render).
        brisque_rectified: BRISQUE/100 of the stored image (NaN when not final).
        pred_psnr_rectified: predicted PSNR of the stored image (the trust model on the
            rectified image; ``pred_psnr`` when the rectifier left the render as it was;
            NaN when not final or trust is off).
        photo_psnr .. pred_psnr: trust scores of the render at the final pose (inherited
            from ``freeviews.trust.TrustScores``; NaN when ``cfg.trust.enabled`` is False).
    """

    candidate: int
    node: int
    world_from_cam: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    brisque: float
    black_ratio: float
    depth_validity: float
    passed: bool
    passed_first: bool
    fail_reasons: str
    n_rect_steps: int = 0
    rect_step: float = math.nan
    final: bool = False
    reference_view: int = -1
    reference_rule: str = ""
    reference_score: float = math.nan
    rectifier: str = ""
    rect_weight: float = 0.0
    brisque_rectified: float = math.nan
    pred_psnr_rectified: float = math.nan


@dataclass
class FreeViewResult:
    """Output of stages 7-10 for one scene.

    Attributes:
        records: one per selected candidate, in the order given.
        final_candidates: ``[F]`` candidate indices of the final views (ascending).
        rgb: ``F`` uint8 ``[H, W, 3]`` images of the final views (rectified).
        depth: ``F`` float32 ``[H, W]`` depths of the final views.
        rgb_render: ``F`` uint8 ``[H, W, 3]`` the same views before image rectification.
        confidence: ``F`` float32 ``[H, W]`` per-pixel confidence in (0, 1) of a rectifier
            that gives one (the ``fixer``); empty otherwise.
        counts: rendered, candidates, passed_first, rescued, rejected, passed, final, scarce,
            re_rendered, reference_renders.
        brisque_threshold: the stage-9 threshold that was applied (BRISQUE/100; predicted PSNR
            in dB with ``final.rank_by = "trust"``; NaN when none applied).
        warnings: messages (e.g. a rectifier backend that was unavailable).
        seed: the seed given.
        timings: exclusive wall-clock seconds per part (``render``, ``render_rectify``,
            ``render_final``, ``render_reference``, ``reference_photo``, ``brisque``,
            ``scores``, ``trust_*``, ``references``, ``rectify``; :class:`StageTimer`).
    """

    records: list[FreeViewRecord]
    final_candidates: np.ndarray
    rgb: list[np.ndarray]
    depth: list[np.ndarray]
    rgb_render: list[np.ndarray]
    counts: dict
    brisque_threshold: float
    warnings: list[str] = field(default_factory=list)
    seed: int = 0
    timings: dict = field(default_factory=dict)
    confidence: list[np.ndarray] = field(default_factory=list)

    @property
    def n_final(self) -> int:
        return int(len(self.final_candidates))

    @property
    def scarce(self) -> bool:
        return bool(self.counts.get("scarce", False))


def final_selection(brisque: np.ndarray, cfg: FinalSelectConfig | None = None
                    ) -> tuple[np.ndarray, float, bool]:
    """Stage 9: stepwise BRISQUE threshold to about ``target`` views.

    The thresholds are tried in order; the first with at least ``target`` views strictly below
    it is applied (keeping all views below it, or the ``target`` best with ``cap_to_target``).
    If none reaches the target, every view is kept and the result is *scarce*.

    Args:
        brisque: ``[P]`` BRISQUE/100 of the views that passed the quality filter.
        cfg: target and thresholds.
    Returns:
        ``(keep [P] bool, threshold applied (NaN when all kept), scarce)``.
    """
    cfg = cfg or FinalSelectConfig()
    b = np.asarray(brisque, dtype=np.float64)
    for t in cfg.thresholds:
        keep = b < t
        if keep.sum() >= cfg.target:
            if cfg.cap_to_target and keep.sum() > cfg.target:
                order = np.lexsort((np.arange(b.size), b))  # by score, ties by position
                keep = np.zeros_like(keep)
                keep[order[:cfg.target]] = True
            return keep, float(t), False
    return np.ones(b.shape, dtype=bool), math.nan, bool(b.size < cfg.target)


def final_selection_trust(pred_psnr: np.ndarray, cfg: FinalSelectConfig | None = None
                          ) -> tuple[np.ndarray, float, bool]:
    """Stage 9 on the predicted PSNR (``rank_by = "trust"``): the stepwise rule of
    :func:`final_selection` with thresholds in dB tried from high to low
    (``cfg.trust_thresholds``), a view kept when its predicted PSNR is >= the threshold;
    ``cap_to_target`` keeps the ``target`` highest (ties by position).

    Returns:
        ``(keep [P] bool, threshold applied (NaN when all kept), scarce)``.
    """
    cfg = cfg or FinalSelectConfig()
    p = np.asarray(pred_psnr, dtype=np.float64)
    for t in cfg.trust_thresholds:
        keep = p >= t
        if keep.sum() >= cfg.target:
            if cfg.cap_to_target and keep.sum() > cfg.target:
                order = np.lexsort((np.arange(p.size), -p))
                keep = np.zeros_like(keep)
                keep[order[:cfg.target]] = True
            return keep, float(t), False
    return np.ones(p.shape, dtype=bool), math.nan, bool(p.size < cfg.target)


def _judge(scores, trust: TrustScores, cfg: FreeViewConfig) -> list[str]:
    """Failed tests of a render under the configured stage-7 rule."""
    if cfg.trust.filter == "paper":
        return failure_reasons(scores, cfg.quality)
    out = []
    if not scores.black_ratio <= cfg.quality.black_ratio_max:
        out.append("black")
    if not trust.pred_psnr >= cfg.trust.min_psnr:
        out.append("trust")
    return out


def _checked(out, h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rgb, depth, alpha = out
    rgb = np.asarray(rgb, dtype=np.float32)
    depth = np.asarray(depth, dtype=np.float32)
    alpha = np.asarray(alpha, dtype=np.float32)
    if rgb.shape != (h, w, 3) or depth.shape != (h, w) or alpha.shape != (h, w):
        raise ShapeError("render_fn output", (rgb.shape, depth.shape, alpha.shape),
                         f"([{h}, {w}, 3], [{h}, {w}], [{h}, {w}])")
    return rgb, depth, alpha


def _render(render_fn: RenderFn, pose: np.ndarray, cams: Cameras, j: int
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    w, h = int(cams.width[j]), int(cams.height[j])
    return _checked(render_fn(np.asarray(pose, dtype=np.float64), float(cams.fx[j]),
                              float(cams.fy[j]), float(cams.cx[j]), float(cams.cy[j]), w, h),
                    h, w)


def _render_many(render_fn: RenderFn, poses: list[np.ndarray], cams: Cameras, js: list[int]
                 ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Renders of ``cams[js[k]]``'s intrinsics at ``poses[k]``: one ``render_fn.batch`` call
    when the render function has one (``stage.make_render_fn``), else view by view."""
    batch = getattr(render_fn, "batch", None)
    if batch is None or len(js) < 2:
        return [_render(render_fn, p, cams, j) for p, j in zip(poses, js)]
    idx = np.asarray(js, dtype=np.int64)
    outs = batch(np.stack([np.asarray(p, np.float64) for p in poses]), cams.fx[idx],
                 cams.fy[idx], cams.cx[idx], cams.cy[idx], cams.width[idx], cams.height[idx])
    if len(outs) != len(js):
        raise ShapeError("render_fn.batch output", (len(outs),), f"[{len(js)}] renders")
    return [_checked(o, int(cams.height[j]), int(cams.width[j])) for o, j in zip(outs, js)]


class StageTimer:
    """Exclusive wall-clock seconds per part of the stage: ``with timer("render"): ...``;
    a part nested in another is not counted in the outer one. ``timer.seconds`` is the
    ``{part: seconds}`` dict (``FreeViewResult.timings``)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._stack: list[list[float]] = []

    @contextmanager
    def __call__(self, part: str):
        self._stack.append([0.0])
        t0 = time.perf_counter()
        try:
            yield
        finally:
            dt = time.perf_counter() - t0
            child = self._stack.pop()[0]
            self.seconds[part] = self.seconds.get(part, 0.0) + dt - child
            if self._stack:
                self._stack[-1][0] += dt


# views rendered per render_fn.batch call (bounds the renders held at once)
RENDER_BATCH = 16


def run_freeviews(
    train_cams: Cameras,
    train_images: Callable[[int], np.ndarray],
    candidates: Cameras,
    selected: np.ndarray,
    edges: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    render_fn: RenderFn,
    cfg: FreeViewConfig | None = None,
    seed: int = 0,
    overlap_fn: Callable[[Cameras], np.ndarray] | None = None,
    progress: Callable[..., None] | None = None,
    grid=None,
    train_masks: Callable[[int], np.ndarray | None] | None = None,
    reserve: np.ndarray | None = None,
) -> FreeViewResult:
    """Stages 7-10 for one scene.

    Args:
        train_cams: T training cameras (graph nodes 0..T-1).
        train_images: ``i -> uint8 [H_i, W_i, 3]`` training photo at ``train_cams`` size.
        candidates: C candidate cameras (graph nodes T..T+C-1).
        selected: ``[S]`` candidate indices kept by NMS (stage 6), rendered in this order.
        edges: view graph ``(src [E], dst [E], wiou [E])`` over node ids, or None (the graph
            reference rule then falls back to pose distance, labelled ``pose_fallback``).
        render_fn: see the module docstring; an optional attribute ``render_fn.batch(poses
            [N, 4, 4], fx [N], fy, cx, cy, width, height) -> N renders`` renders many cameras
            in one call (same output as N calls).
        cfg: stage configuration (paper defaults when None).
        seed: recorded; the stage is deterministic.
        overlap_fn: ``cams -> [n, T]`` WIoU of cameras with the training views at any pose
            (``references.TrainOverlap``); with it the graph reference rule takes the best
            direct training neighbour at each final view's *final* pose
            (``cfg.reference.overlap = "final_pose"``). Without it the stored ``edges`` are
            used.
        progress: optional ``progress(done, total, phase=...)`` after each rendered candidate
            (``phase="render+filter"``) and each final view (``phase="rectify"``).
        grid: the certainty grid for the trust scores (``select.certainty.CertaintyGrid``);
            None takes ``overlap_fn.grid`` when there is one, else the certainty scores are
            NaN.
        train_masks: ``i -> [H_i, W_i]`` bool object mask of training photo ``i`` (None: no
            masks). A masked photo is handed to the trust scores and the rectifier with its
            mask as a 4th channel (0 / 255): the photometric consistency and the reprojection
            use only its mask pixels. The stage-7 black/empty limit becomes
            ``quality.black_ratio_max`` + the largest background share of the training masks
            (capped at 1): an object capture's free views are mostly empty background.
        reserve: ``[R]`` further candidate indices in the order they may be drawn (the
            selection's ``reserve``: what NMS would accept next at relaxed thresholds). While
            fewer than ``cfg.final.target`` views have passed, the next
            :data:`RENDER_BATCH` reserve candidates are rendered and scored like the selected
            ones (records in draw order after the selected ones; ``counts["reserve_drawn"]``).
    Returns:
        The per-view table, the final images, the counts and ``timings`` (seconds per part).
    """
    cfg = cfg or FreeViewConfig()
    timer = StageTimer()
    T, C = len(train_cams), len(candidates)
    selected = np.asarray(selected, dtype=np.int64).ravel()
    reserve = (np.zeros(0, np.int64) if reserve is None
               else np.asarray(reserve, dtype=np.int64).ravel())
    for name, arr in (("selected", selected), ("reserve", reserve)):
        if arr.size and (arr.min() < 0 or arr.max() >= C):
            raise ValueError(f"{name} candidate indices must lie in [0, {C}), got "
                             f"[{arr.min()}, {arr.max()}]")
    if len(np.unique(selected)) != selected.size:
        raise ValueError("selected candidate indices contain duplicates")
    both = np.concatenate([selected, reserve])
    if len(np.unique(both)) != both.size:
        raise ValueError("reserve candidate indices repeat or overlap the selected ones")
    scale = cfg.render_scale
    cams = candidates.scaled(scale) if scale != 1.0 else candidates
    tcams = train_cams.scaled(scale) if scale != 1.0 else train_cams
    graph = None
    if edges is not None:
        graph = ViewGraph.from_edges(T, T + C, *edges)
    warn: list[str] = []
    try:
        rectifier = make_rectifier(cfg.rectifier)
    except RectifierUnavailable as e:
        msg = f"image rectifier {cfg.rectifier.backend!r} unavailable, using 'none': {e}"
        warnings.warn(msg, RuntimeWarning, stacklevel=2)
        warn.append(msg)
        rectifier = NoneRectifier()

    train_poses = tcams.world_from_cam
    ref_cache: dict[int, tuple[np.ndarray, RenderedView]] = {}

    def reference(i: int) -> tuple[np.ndarray, RenderedView]:
        if i not in ref_cache:
            ref_cache[i] = _reference(i, train_cams, tcams, train_images, render_fn,
                                      train_masks, timer)
        return ref_cache[i]

    if train_masks is not None:
        # An object capture: its background is meant to stay empty, so a free view of the
        # object is mostly empty too. The black/empty limit is raised by the training photos'
        # largest background share (an empty view still fails: depth validity, trust).
        bg_share = max(1.0 - float(np.mean(np.asarray(train_masks(i), bool)))
                       for i in range(T))
        lim = min(1.0, bg_share + cfg.quality.black_ratio_max)
        cfg = cfg.model_copy(update={"quality": cfg.quality.model_copy(
            update={"black_ratio_max": lim})})
    if grid is None:
        grid = getattr(overlap_fn, "grid", None)
    trust_ctx = None
    if cfg.trust.enabled:
        trust_ctx = TrustContext(train_poses, tcams.fx, tcams.fy, tcams.cx, tcams.cy,
                                 tcams.width, tcams.height, reference, grid, cfg.trust,
                                 timer=timer)

    def score(r, pose, j):
        with timer("scores"):
            with timer("brisque"):
                u8 = to_uint8(r[0])
                b = brisque_score(u8)
            s = QualityScores(brisque=b, black_ratio=black_ratio(r[0], r[2],
                                                                 cfg.quality.empty_alpha),
                              depth_validity=depth_validity(r[1], r[2], cfg.quality.crop,
                                                            cfg.quality.depth_alpha,
                                                            cfg.quality.min_valid_fraction))
        t = TrustScores()
        if trust_ctx is not None:
            t = trust_ctx(RenderedView(r[0], r[1], r[2], pose, float(cams.fx[j]),
                                       float(cams.fy[j]), float(cams.cx[j]), float(cams.cy[j])),
                          s.brisque, s.black_ratio, s.depth_validity)
        return s, t

    records: list[FreeViewRecord] = []
    cache: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    budget = cfg.cache_mb * 2**20
    n_render = 0
    n_passed = 0
    n_drawn = 0

    def process(js: list[int]) -> None:
        """Stages 7-8 on a batch: render all at their poses, score; the failures are
        re-rendered step by step (one batch per step) until each passes or runs out."""
        nonlocal n_render, n_passed, budget
        poses = [cams.world_from_cam[j] for j in js]
        with timer("render"):
            rs = _render_many(render_fn, poses, cams, js)
        n_render += len(js)
        st = []
        for j, pose, r in zip(js, poses, rs):
            scores, trust = score(r, pose, j)
            reasons = _judge(scores, trust, cfg)
            st.append({"pose": pose, "r": r, "scores": scores, "trust": trust,
                       "reasons": reasons, "ok": not reasons, "n_steps": 0,
                       "step": math.nan})
        steps = {}
        for k, v in enumerate(st):
            if not v["ok"]:
                ref_i = nearest_training_camera(train_poses, v["pose"])
                steps[k] = list(rectification_poses(v["pose"], train_poses[ref_i], cfg.pose))
        level = 0
        todo = [k for k in steps if steps[k]]
        while todo:
            ps = [steps[k][level][1] for k in todo]
            with timer("render_rectify"):
                rr = _render_many(render_fn, ps, cams, [js[k] for k in todo])
            n_render += len(todo)
            nxt = []
            for k, p, r in zip(todo, ps, rr):
                v = st[k]
                v["n_steps"] += 1
                s, t = score(r, p, js[k])
                if not _judge(s, t, cfg):
                    v.update(ok=True, step=steps[k][level][0], pose=p, scores=s, trust=t, r=r)
                elif level + 1 < len(steps[k]):
                    nxt.append(k)
            todo = nxt
            level += 1
        for j, v in zip(js, st):
            if v["ok"]:
                n_passed += 1
                nbytes = sum(a.nbytes for a in v["r"])
                if budget >= nbytes:
                    cache[j] = v["r"]
                    budget -= nbytes
            sc = v["scores"]
            records.append(FreeViewRecord(
                candidate=j, node=T + j, world_from_cam=np.array(v["pose"], dtype=np.float64),
                fx=float(cams.fx[j]), fy=float(cams.fy[j]), cx=float(cams.cx[j]),
                cy=float(cams.cy[j]), width=int(cams.width[j]), height=int(cams.height[j]),
                brisque=sc.brisque, black_ratio=sc.black_ratio,
                depth_validity=sc.depth_validity, passed=v["ok"],
                passed_first=not v["reasons"], fail_reasons=",".join(v["reasons"]),
                n_rect_steps=v["n_steps"], rect_step=v["step"], **v["trust"].as_dict()))
            if progress is not None:
                progress(len(records), int(selected.size + n_drawn), phase="render+filter",
                         passed=n_passed, renders=n_render)

    sel_list = [int(j) for j in selected]
    for start in range(0, len(sel_list), RENDER_BATCH):
        process(sel_list[start:start + RENDER_BATCH])
    res_list = [int(j) for j in reserve]
    while n_passed < cfg.final.target and n_drawn < len(res_list):
        js = res_list[n_drawn:n_drawn + RENDER_BATCH]
        n_drawn += len(js)
        process(js)

    # stage 9
    passed_idx = [k for k, r in enumerate(records) if r.passed]
    if cfg.final.rank_by == "trust":
        keep, threshold, scarce = final_selection_trust(
            np.array([records[k].pred_psnr for k in passed_idx]), cfg.final)
    else:
        keep, threshold, scarce = final_selection(
            np.array([records[k].brisque for k in passed_idx]), cfg.final)
    final_rows = sorted((passed_idx[k] for k in np.flatnonzero(keep)),
                        key=lambda k: records[k].candidate)
    scarce = scarce or len(final_rows) < cfg.final.target

    # stage 10
    overlap = None
    if (rectifier.needs_reference and overlap_fn is not None and cfg.reference.rule == "graph"
            and cfg.reference.overlap == "final_pose" and final_rows):
        fr = [records[k] for k in final_rows]
        fcams = Cameras(np.stack([r.world_from_cam for r in fr]), [r.fx for r in fr],
                        [r.fy for r in fr], [r.cx for r in fr], [r.cy for r in fr],
                        [r.width for r in fr], [r.height for r in fr])
        with timer("references"):
            overlap = np.asarray(overlap_fn(fcams), dtype=np.float64)
        if overlap.shape != (len(fr), T):
            raise ShapeError("overlap_fn output", overlap.shape, f"[{len(fr)}, {T}]")
    missing = [k for k in final_rows if records[k].candidate not in cache]
    for start in range(0, len(missing), RENDER_BATCH):
        ks = missing[start:start + RENDER_BATCH]
        with timer("render_final"):
            rr = _render_many(render_fn, [records[k].world_from_cam for k in ks], cams,
                              [records[k].candidate for k in ks])
        for k, r in zip(ks, rr):
            cache[records[k].candidate] = r  # released below, view by view
    n_rerender = len(missing)
    out_rgb, out_depth, out_render, out_conf = [], [], [], []
    for n_k, k in enumerate(final_rows):
        rec = records[k]
        rec.final = True
        j = rec.candidate
        rgb, depth, alpha = cache.pop(j)
        view = RenderedView(rgb, depth, alpha, rec.world_from_cam, rec.fx, rec.fy, rec.cx, rec.cy)
        ref_photo = ref_view = None
        if rectifier.needs_reference:
            with timer("references"):
                choice = select_reference(cfg.reference, train_poses, rec.world_from_cam,
                                          graph, rec.node,
                                          None if overlap is None else overlap[n_k])
            rec.reference_view, rec.reference_rule = choice.train_index, choice.rule
            rec.reference_score = choice.score
            ref_photo, ref_view = reference(choice.train_index)
            n_ref = int(getattr(rectifier, "n_references", 1))
            if n_ref > 1:  # the chosen reference, then the nearest others by pose distance
                order = np.argsort(pose_distances(train_poses, rec.world_from_cam),
                                   kind="stable")
                more = [reference(int(i)) for i in order
                        if int(i) != choice.train_index][: n_ref - 1]
                ref_photo = [ref_photo] + [p for p, _ in more]
                ref_view = [ref_view] + [v for _, v in more]
        with timer("rectify"):
            res = rectifier(view, ref_photo, ref_view)
        rec.rectifier = rectifier.name
        rec.rect_weight = float(res.weight.mean())
        with timer("brisque"):
            u8 = to_uint8(res.rgb)
            render_u8 = to_uint8(rgb)
            # the stored image is the render (e.g. the 'none' rectifier): its score is known
            same = np.array_equal(u8, render_u8)
            rec.brisque_rectified = rec.brisque if same else brisque_score(u8)
        if trust_ctx is not None:  # trust of the stored image, as the downstream flows see it
            if same:
                rec.pred_psnr_rectified = rec.pred_psnr
            else:
                t2 = trust_ctx(RenderedView(u8.astype(np.float32) / 255.0, res.depth, alpha,
                                            rec.world_from_cam, rec.fx, rec.fy, rec.cx, rec.cy),
                               rec.brisque_rectified, rec.black_ratio, rec.depth_validity)
                rec.pred_psnr_rectified = float(t2.pred_psnr)
        out_rgb.append(u8)
        out_depth.append(np.asarray(res.depth, dtype=np.float32))
        out_render.append(render_u8)
        if getattr(rectifier, "gives_confidence", False):
            out_conf.append(np.asarray(res.weight, np.float32))
        if progress is not None:
            progress(n_k + 1, len(final_rows), phase="rectify")

    n_first = sum(r.passed_first for r in records)
    n_cand = len(records)
    counts = {
        "candidates": n_cand, "rendered": n_render, "passed_first": n_first,
        "rescued": n_passed - n_first, "rejected": n_cand - n_passed,
        "passed": n_passed, "final": len(final_rows), "scarce": bool(scarce),
        "re_rendered": n_rerender, "reference_renders": len(ref_cache),
        "reserve_drawn": n_drawn,
    }
    return FreeViewResult(records, np.array([records[k].candidate for k in final_rows],
                                            dtype=np.int64),
                          out_rgb, out_depth, out_render, counts, threshold, warn, int(seed),
                          timings=dict(timer.seconds), confidence=out_conf)


def _reference(i: int, train_cams: Cameras, tcams: Cameras, train_images, render_fn,
               train_masks=None, timer=None) -> tuple[np.ndarray, RenderedView]:
    """Photo of training view ``i`` (at the render scale) and its render (for its depth);
    with ``train_masks`` the photo has the object mask as a 4th channel (0 / 255)."""
    with timer("reference_photo") if timer is not None else nullcontext():
        return _reference_timed(i, train_cams, tcams, train_images, render_fn, train_masks,
                                timer)


def _reference_timed(i, train_cams, tcams, train_images, render_fn, train_masks, timer):
    photo = np.asarray(train_images(i))
    h0, w0 = int(train_cams.height[i]), int(train_cams.width[i])
    if photo.ndim != 3 or photo.shape[:2] != (h0, w0) or photo.shape[2] < 3:
        raise ShapeError(f"train_images({i})", photo.shape, f"[{h0}, {w0}, 3] uint8")
    photo = photo[..., :3]
    h, w = int(tcams.height[i]), int(tcams.width[i])
    if (h, w) != (h0, w0):
        photo = cv2.resize(photo, (w, h), interpolation=cv2.INTER_AREA)
    mask = None if train_masks is None else train_masks(i)
    if mask is not None:
        from freescale_core.scene.io.masks import resize_mask

        mask = np.asarray(mask, bool)
        if mask.shape != (h0, w0):
            raise ShapeError(f"train_masks({i})", mask.shape, f"[{h0}, {w0}] bool")
        a = np.where(resize_mask(mask, w, h), 255, 0).astype(photo.dtype)
        photo = np.concatenate([photo, a[..., None]], axis=-1)
    with timer("render_reference") if timer is not None else nullcontext():
        rgb, depth, alpha = _render(render_fn, tcams.world_from_cam[i], tcams, i)
    view = RenderedView(rgb, depth, alpha, tcams.world_from_cam[i], float(tcams.fx[i]),
                        float(tcams.fy[i]), float(tcams.cx[i]), float(tcams.cy[i]))
    return photo, view


# --------------------------------------------------------------------------- stage entry point
def make_render_fn(g: Gaussians, background=(0.0, 0.0, 0.0), backend: str = "auto"):
    """``render_fn(world_from_cam, fx, fy, cx, cy, width, height) -> (rgb, depth, alpha)``.

    ``background`` and ``backend`` must be the reconstruction's (``ReconConfig.background``,
    ``ReconConfig.raster_backend``): a model trained on white renders its free views on white.
    ``render_fn.batch(world_from_cam [N, 4, 4], fx [N], ..., height [N])`` renders N cameras
    in one rasterizer call (``raster.render_gaussians_batch``, the same images).
    """
    from freescale_core.raster import render_gaussians, render_gaussians_batch

    bg = tuple(float(v) for v in background)

    def render_fn(world_from_cam, fx, fy, cx, cy, width, height):
        return render_gaussians(g, world_from_cam, fx, fy, cx, cy, int(width), int(height),
                                background=bg, backend=backend)

    def batch(world_from_cam, fx, fy, cx, cy, width, height):
        return render_gaussians_batch(g, world_from_cam, fx, fy, cx, cy, width, height,
                                      background=bg, backend=backend)

    render_fn.batch = batch
    return render_fn


def make_overlap_fn(sel, train_cams, cfg):
    """The graph reference rule's WIoU at the final pose (``references.TrainOverlap``) over
    the selection's certainty grid, or None when the rule does not need it or the selection
    has no grid. ``cfg`` is a ``FreeViewConfig``; the visibility rule is the selection's
    (``sel.config["visibility"]``) unless ``cfg.reference.visibility`` names one."""
    ref = cfg.reference
    if ref.rule != "graph" or ref.overlap != "final_pose" or getattr(sel, "grid", None) is None:
        return None
    from schemas.select import VisibilityConfig

    from freescale_core.freeviews.references import TrainOverlap

    vis = VisibilityConfig.model_validate((getattr(sel, "config", None) or {}).get(
        "visibility", {}))
    if ref.visibility != "selection":
        vis = vis.model_copy(update={"mode": ref.visibility})
    return TrainOverlap(sel.grid, train_cams, vis, ref.overlap_angle_deg)


def run_free_view_stage(scene: Scene, g: Gaussians, sel, cfg, seed: int = 0,
                        scene_path: str | Path | None = None,
                        train_scale: float = 1.0, background=(0.0, 0.0, 0.0),
                        backend: str = "auto", progress=None) -> FreeViewResult:
    """Stages 7-10 on the NMS-selected candidates of ``sel`` (a ``SelectionResult``), then
    on its reserve (``sel.reserve``, in order) while fewer than ``cfg.final.target`` passed.

    Free views are rendered at the reconstruction's training resolution (METHOD stage 7):
    the effective render scale is ``min(cfg.render_scale, train_scale)``, where
    ``train_scale`` is the factor the reconstruction trained at. Rendering a 128-px model at
    640 px only manufactures blur (BRISQUE ~0.9 on kermit, every view rejected).

    When the scene carries a ground-truth oracle (the sample scene), each final view's PSNR
    against the true image at the same pose is recorded (before and after image
    rectification) in ``result.gt`` as ``{candidate: (psnr_render, psnr_final)}``, its
    seconds in ``result.timings["ground_truth"]``.
    """
    T = int(sel.n_train)
    cand = np.asarray(sel.selected, dtype=np.int64) - T
    edges = (sel.edges.src, sel.edges.dst, sel.edges.wiou)
    scale = float(min(cfg.render_scale, train_scale))
    if scale != cfg.render_scale:
        cfg = cfg.model_copy(update={"render_scale": scale})
    reserve = np.asarray(getattr(sel, "reserve", np.zeros(0)), dtype=np.int64) - T
    fv = run_freeviews(scene.cameras, scene.load_image, sel.candidates, cand, edges,
                       make_render_fn(g, background, backend), cfg, seed=seed,
                       overlap_fn=make_overlap_fn(sel, scene.cameras, cfg), progress=progress,
                       grid=getattr(sel, "grid", None),
                       train_masks=scene.load_mask if scene.has_masks else None,
                       reserve=reserve)
    fv.gt = {}
    oracle = ground_truth_oracle(scene_path)
    if oracle is not None:
        t0 = time.perf_counter()
        recs = {r.candidate: r for r in fv.records}
        for k, c in enumerate(fv.final_candidates):
            r = recs[int(c)]
            true_rgb, _ = oracle.render(r.world_from_cam, r.fx, r.fy, r.cx, r.cy, r.width, r.height)
            fv.gt[int(c)] = (psnr_u8(fv.rgb_render[k], true_rgb), psnr_u8(fv.rgb[k], true_rgb))
        # an evaluation of the sample scene, not stage work: its own part of the timings
        fv.timings["ground_truth"] = time.perf_counter() - t0
    return fv
