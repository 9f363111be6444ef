"""Which views form one LVSM training example (METHOD.md "Downstream uses": LVSM training).

An example is ``n_input`` input views and ``n_target`` target views of one scene. Two branches:

* **frames** (always available): a window of captured frames is cut from the capture order and
  the views are drawn inside it. The window's *span* D (frame distance from its first to its
  last view) follows a curriculum: drawn uniformly from a range that moves linearly from
  ``warmup_frame_dist`` (step 0) to ``frame_dist`` (step >= ``warmup_steps``).
* **graph** (probability ``graph_prob`` when ``use_free_views``): the example is grown along the
  FreeScale view graph (captured + free views, edges weighted by WIoU). During warm-up it starts
  from nodes of high total WIoU and follows high-WIoU edges (small motion); after warm-up it
  follows low-WIoU edges (large motion). ``random_free`` (arm D) replaces the walk by a uniform
  draw over the scene's views.

Free-view targets carry ``novel_target_weight`` as loss weight, captured targets 1.

The curriculum step lives in shared memory (a ``multiprocessing.RawValue`` created with
the sampler), so ``set_step`` in the training process reaches DataLoader workers, forked or spawned,
persistent or not; ``sample(..., step=...)`` passes an explicit step instead. Everything random
comes from the ``numpy.random.Generator`` the caller passes: same generator state, same sample.
"""

from __future__ import annotations

import multiprocessing as mp
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from freescale_core.store.scene_views import SceneViews
from schemas.lvsm import LVSMSamplerConfig

__all__ = ["SceneViews", "Sample", "ViewSampler"]

Source = Literal["frames", "graph", "random"]


@dataclass(frozen=True)
class Sample:
    """One training example: view ids into ``SceneViews``.

    Attributes:
        input_ids: ``[n_input]`` int64; frame branch: in capture order; graph branch: in the
            order the walk added them (``input_ids[0]`` is the seed).
        target_ids: ``[n_target]`` int64.
        target_weight: ``[n_target]`` float32 loss weights (1 captured, novel_target_weight free).
        source: "frames" | "graph" | "random" (the arm-D uniform draw that replaces the walk).
        step: curriculum step the sample was drawn at.
        span: frame branch: frame distance D from the window's first to last view (captured
            frames); -1 otherwise.
        edge_wiou: graph branch: ``[n_input + n_target - 1]`` WIoU of the edge that attached
            each view after the seed, in order; empty otherwise.
        swapped: True when a free-only draw had an input replaced by a captured view.
    """

    input_ids: np.ndarray
    target_ids: np.ndarray
    target_weight: np.ndarray
    source: Source
    step: int = 0
    span: int = -1
    edge_wiou: np.ndarray = field(default_factory=lambda: np.zeros(0))
    swapped: bool = False


class ViewSampler:
    """Draws LVSM examples from a scene (frames and view-graph branches, with a curriculum).

    Args:
        config: sampler settings (default ``LVSMSamplerConfig()``: the paper's).
        **overrides: config fields to override.

    Create the sampler before the DataLoader starts its workers (its step counter is shared
    memory inherited or pickled into them at start); then ``set_step`` in the training loop.
    A sampler is pickled only while a process is being started (like any
    ``multiprocessing.RawValue``); pickling it otherwise raises instead of silently detaching
    the step.
    """

    def __init__(self, config: LVSMSamplerConfig | None = None, **overrides) -> None:
        cfg = config or LVSMSamplerConfig()
        if overrides:
            cfg = LVSMSamplerConfig.model_validate({**cfg.model_dump(), **overrides})
        self.config = cfg
        # Shared int64 step without a lock: one writer (the training loop), aligned 8-byte
        # stores; a lock would be a SemLock, which Python >= 3.12 refuses to pass from the
        # default fork context to spawned workers.
        self._step = mp.RawValue("q", 0)

    # ------------------------------------------------------------------ curriculum
    def set_step(self, step: int) -> None:
        """Set the curriculum step; visible at once in every DataLoader worker."""
        self._step.value = int(step)

    @property
    def step(self) -> int:
        """Current shared curriculum step."""
        return int(self._step.value)

    def in_warmup(self, step: int | None = None) -> bool:
        """True while ``step < warmup_steps`` (graph branch prefers high WIoU)."""
        return (self.step if step is None else step) < self.config.warmup_steps

    def frame_range(self, n_captured: int, step: int | None = None) -> tuple[int, int]:
        """Inclusive range of the frame-branch span D at ``step`` for a capture of n views.

        Rule: interpolate linearly between ``warmup_frame_dist`` (step 0) and ``frame_dist``
        (step >= warmup_steps); multiply by ``n_captured / reference_length`` (no scaling when
        reference_length is None); round; clamp to ``[n_input + n_target - 1, n_captured - 1]``
        (the fewest frames that hold every view, the longest window the capture allows). So a
        short capture never fails: its scaled range is lifted to the smallest span that holds
        the example, and a range beyond the capture (reference_length None) is cut to the
        capture's length.
        """
        c = self.config
        step = self.step if step is None else step
        a = 1.0 if c.warmup_steps == 0 else min(max(step, 0) / c.warmup_steps, 1.0)
        lo = (1 - a) * c.warmup_frame_dist[0] + a * c.frame_dist[0]
        hi = (1 - a) * c.warmup_frame_dist[1] + a * c.frame_dist[1]
        s = 1.0 if c.reference_length is None else n_captured / c.reference_length
        d_min, d_max = c.n_views - 1, n_captured - 1
        lo_i = int(np.clip(round(lo * s), d_min, d_max))
        hi_i = int(np.clip(round(hi * s), lo_i, d_max))
        return lo_i, hi_i

    # ------------------------------------------------------------------ sampling
    def sample(self, scene: SceneViews, rng: np.random.Generator,
               step: int | None = None) -> Sample:
        """Draw one example.

        Args:
            scene: the scene's views and view graph.
            rng: source of all randomness.
            step: curriculum step; None = the shared step (``set_step``).

        Raises:
            ValueError: the scene has fewer than n_input + n_target captured views.
        """
        c = self.config
        step = self.step if step is None else int(step)
        n_cap = int(np.count_nonzero(~scene.is_free))
        if n_cap < c.n_views:
            raise ValueError(f"scene {scene.scene_id!r} has {n_cap} captured views; the LVSM "
                             f"sampler needs at least n_input + n_target = {c.n_views}")
        if c.use_free_views and c.graph_prob > 0 and rng.random() < c.graph_prob:
            s = (self._random_branch(scene, rng, step) if c.random_free
                 else self._graph_branch(scene, rng, step))
            if s is not None:
                return s
        return self._frame_branch(scene, rng, step)

    def _finish(self, scene: SceneViews, ids: np.ndarray, source: Source, step: int,
                **extra) -> Sample:
        """Split ``ids`` ([n_views], inputs first) into a Sample with target weights."""
        n_in = self.config.n_input
        inp, tgt = ids[:n_in].astype(np.int64), ids[n_in:].astype(np.int64)
        w = np.where(scene.is_free[tgt], self.config.novel_target_weight, 1.0)
        if scene.view_weight is not None:  # per-free-view trust (issue 19)
            w = np.where(scene.is_free[tgt], w * scene.view_weight[tgt], w)
        w = w.astype(np.float32)
        return Sample(inp, tgt, w, source, step, **extra)

    def _frame_branch(self, scene: SceneViews, rng: np.random.Generator, step: int) -> Sample:
        """Captured views from a window of span D (see ``frame_range``); never recurses.

        "between": the window's first and last frames are inputs, the other inputs and all
        targets are distinct frames drawn uniformly strictly inside. "extrapolate": the window's
        two ends plus distinct interior frames are shuffled and split into inputs and targets,
        so a target may lie before or after every input.
        """
        c = self.config
        order = scene.captured_order  # [N_captured]
        lo, hi = self.frame_range(order.size, step)
        D = int(rng.integers(lo, hi + 1))
        s = int(rng.integers(0, order.size - D))  # window [s, s + D] of capture ranks
        interior = s + 1 + rng.choice(D - 1, size=c.n_views - 2, replace=False)  # [n_views-2]
        if c.target_mode == "between":
            inp = np.sort(np.concatenate([[s, s + D], interior[: c.n_input - 2]]))
            tgt = interior[c.n_input - 2:]
        else:
            pos = rng.permutation(np.concatenate([[s, s + D], interior]))  # [n_views]
            inp, tgt = np.sort(pos[: c.n_input]), pos[c.n_input:]
        return self._finish(scene, order[np.concatenate([inp, tgt])], "frames", step, span=D)

    def _graph_branch(self, scene: SceneViews, rng: np.random.Generator,
                      step: int) -> Sample | None:
        """Grow a connected set of views along the view graph; None when it cannot.

        Seed: during warm-up drawn with probability proportional to strength^t (strength =
        total WIoU of a node's edges), after warm-up uniformly; only nodes whose connected
        component holds n_input + n_target views qualify. Growth: repeatedly draw one edge
        leaving the chosen set with probability proportional to wiou^t (warm-up) or
        (1 - wiou)^t (after) and add its far end; the first n_input views are the inputs,
        targets are attached by edges leaving the inputs (any chosen view if none leave them).
        The draw is the preference: nothing reorders the result afterwards.

        A set of free views only has its last input replaced by a captured view at the fewest
        hops (<= swap_hops) from the set, drawn uniformly among those. Returns None (the
        caller uses the frame branch) when no component is large enough or no captured view is
        near a free-only set.
        """
        c = self.config
        src, dst, w = scene.edges
        n, k = scene.n_views, c.n_views
        if src.size == 0:
            return None
        adj = coo_matrix((np.ones(src.size), (src, dst)), shape=(n, n))
        _, label = connected_components(adj, directed=False)
        comp_size = np.bincount(label)[label]  # [N]
        deg = np.bincount(src, minlength=n) + np.bincount(dst, minlength=n)  # [N]
        eligible = np.flatnonzero((deg > 0) & (comp_size >= k))
        if eligible.size == 0:
            return None
        warm = self.in_warmup(step)
        t = c.graph_sharpness
        if warm:
            strength = np.bincount(src, w, n) + np.bincount(dst, w, n)  # [N]
            seed = int(rng.choice(eligible, p=_normalised(strength[eligible] ** t)))
        else:
            seed = int(rng.choice(eligible))
        pref = w ** t if warm else (1.0 - w) ** t  # [E]

        chosen = np.zeros(n, bool)
        is_input = np.zeros(n, bool)
        chosen[seed] = is_input[seed] = True
        ids, used_w = [seed], []
        for i in range(1, k):
            from_set = is_input if i >= c.n_input else chosen
            e = np.flatnonzero((from_set[src] & ~chosen[dst]) | (from_set[dst] & ~chosen[src]))
            if e.size == 0:  # targets: no edge leaves the inputs -> any chosen view
                e = np.flatnonzero(chosen[src] ^ chosen[dst])
            j = int(rng.choice(e, p=_normalised(pref[e])))
            new = int(dst[j] if chosen[src[j]] else src[j])
            chosen[new] = True
            is_input[new] = i < c.n_input
            ids.append(new)
            used_w.append(w[j])
        ids_arr = np.asarray(ids, np.int64)  # [k]
        swapped = False
        if scene.is_free[ids_arr].all():
            near = _nearest_captured(scene, chosen, c.swap_hops)
            if near.size == 0:
                return None
            ids_arr[c.n_input - 1] = rng.choice(near)
            swapped = True
        return self._finish(scene, ids_arr, "graph", step,
                            edge_wiou=np.asarray(used_w, np.float64), swapped=swapped)

    def _random_branch(self, scene: SceneViews, rng: np.random.Generator, step: int) -> Sample:
        """Arm D: n_input + n_target distinct views drawn uniformly from all the scene's views;
        a free-only draw has its last input replaced by a uniformly drawn captured view."""
        c = self.config
        ids = rng.choice(scene.n_views, size=c.n_views, replace=False).astype(np.int64)
        swapped = False
        if scene.is_free[ids].all():
            ids[c.n_input - 1] = rng.choice(np.flatnonzero(~scene.is_free))
            swapped = True
        return self._finish(scene, ids, "random", step, swapped=swapped)


def _normalised(p: np.ndarray) -> np.ndarray | None:
    """Probabilities proportional to ``p`` (None = uniform when they sum to 0)."""
    total = float(p.sum())
    return p / total if total > 0 else None


def _nearest_captured(scene: SceneViews, chosen: np.ndarray, hops: int) -> np.ndarray:
    """Captured views not in ``chosen`` at the fewest hops (<= ``hops``) from it."""
    src, dst, _ = scene.edges
    reached = chosen.copy()  # [N]
    frontier = chosen.copy()  # [N]
    for _ in range(hops):
        nxt = np.zeros_like(frontier)
        nxt[dst[frontier[src]]] = True
        nxt[src[frontier[dst]]] = True
        nxt &= ~reached
        hit = np.flatnonzero(nxt & ~scene.is_free)
        if hit.size:
            return hit
        reached |= nxt
        frontier = nxt
    return np.zeros(0, np.int64)
