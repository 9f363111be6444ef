"""Export to LVSM's scene dataset layout (the layout its ``data/dataset_scene.py`` reads).

::

    OUT/images/<scene>/00000.png ...        one PNG per frame, at the view's own size
    OUT/metadata/<scene>.json               {"scene_name", "frames": [{"image_path",
                                             "fxfycxcy", "w2c", "freescale": {...}}]}
    OUT/full_list.txt                       absolute paths of the metadata files
    OUT/evaluation_index.json               {scene: {"context": [i, j], "target": [...]}}

* ``fxfycxcy`` are pixels of that frame's image; ``w2c`` is ``cam_from_world`` (OpenCV axes,
  4x4), LVSM's convention. ``image_path`` is absolute (LVSM opens it as given).
* Frame order: the captured views in capture order first (LVSM's frame-distance sampler picks
  a start frame and an end frame ``[min_frame_dist, max_frame_dist]`` apart in this list, so
  the captured part must be a sequence), then the free views in view-id order. Each frame's
  ``freescale`` record (``view_id``, ``is_free``, ``mode``, ``capture_index``) lets the
  FreeScale view-graph sampler find them.
* ``evaluation_index.json`` is LVSM's view-index format (its ``inference.view_idx_file_path``),
  chosen from the view graph by :func:`choose_eval_views`; a scene without a usable pair maps
  to ``null`` (LVSM skips it).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from freescale_core.exports.common import (ExportResult, atomic_dir, frame_order, scene_sets,
                                           write_png)
from freescale_core.geometry.cameras import lvsm_frame


def choose_eval_views(fvs, n_context: int = 2, n_target: int = 3,
                      min_wiou: float = 0.3) -> tuple[list[int], list[int]] | None:
    """Context and target frames (positions in the export's frame list) from the view graph.

    Context: among pairs of captured views joined by an edge with WIoU >= ``min_wiou``, the
    pair farthest apart in capture order (a wide but overlapping baseline; the highest-WIoU
    captured pair when none reaches ``min_wiou``); ``n_context`` > 2 adds the captured views
    between them, evenly spaced. Targets: the other views (free views included) ranked by
    their smallest WIoU to any context view, highest first (views that the context sees).
    Returns None when the scene has fewer than ``n_context + 1`` views or no captured pair.
    """
    v = fvs.dataset_views()
    order = frame_order(fvs)
    pos = {int(v.view_id[r]): k for k, r in enumerate(order)}
    if len(order) < n_context + 1:
        return None
    src, dst, w = fvs.graph()
    W = np.zeros((len(order), len(order)))
    for s, d, x in zip(src, dst, w):
        W[pos[int(s)], pos[int(d)]] = W[pos[int(d)], pos[int(s)]] = x
    n_cap = int((~v.is_free).sum())
    if n_cap < 2:
        return None
    cap = W[:n_cap, :n_cap]
    iu, ju = np.triu_indices(n_cap, 1)
    wu = cap[iu, ju]
    if not (wu > 0).any():
        a, b = 0, n_cap - 1
    else:
        ok = wu >= min_wiou
        if ok.any():
            k = np.flatnonzero(ok)[np.argmax((ju - iu)[ok])]
        else:
            k = int(np.argmax(wu))
        a, b = int(iu[k]), int(ju[k])
    ctx = [a, b] if n_context <= 2 else sorted(set(np.linspace(a, b, n_context).round().astype(int).tolist()))
    rest = np.array([k for k in range(len(order)) if k not in ctx])
    score = W[np.ix_(rest, ctx)].min(axis=1)
    tgt = rest[np.argsort(-score, kind="stable")[:n_target]]
    return [int(c) for c in ctx], sorted(int(t) for t in tgt)


def export_scene(fvs, root_final: Path, tmp: Path) -> tuple[dict, dict]:
    """Images + metadata of one scene. Paths in the metadata point at ``root_final``."""
    v = fvs.dataset_views()
    cams = v.cameras
    frames = []
    n_free = 0
    for k, r in enumerate(frame_order(fvs)):
        vid = int(v.view_id[r])
        rel = Path("images") / fvs.scene_id / f"{k:05d}.png"
        write_png(tmp / rel, fvs.rgb(vid))
        n_free += int(v.is_free[r])
        fr = {"image_path": str(root_final / rel),
              **lvsm_frame(cams.world_from_cam[r], cams.fx[r], cams.fy[r], cams.cx[r],
                           cams.cy[r]),
              "freescale": {"view_id": vid, "is_free": bool(v.is_free[r]),
                            "mode": str(v.mode[r]), "capture_index": int(v.capture_index[r])}}
        frames.append(fr)
    meta = {"scene_name": fvs.scene_id, "frames": frames}
    return meta, {"train": len(frames) - n_free, "free": n_free}


def export(store_root, out, scenes: list[str] | None = None, n_context: int = 2,
           n_target: int = 3, overwrite: bool = False) -> ExportResult:
    sets = scene_sets(store_root, scenes)
    bad = [s.scene_id for s in sets if "." in s.scene_id]
    if bad:  # LVSM derives the scene name from the metadata file name up to the first dot
        raise ValueError(f"scene ids {bad} contain '.', which LVSM's view index cannot match")
    final = Path(out).absolute()
    res = ExportResult("lvsm", final, [s.scene_id for s in sets])
    index: dict = {}
    with atomic_dir(final, overwrite) as tmp:
        (tmp / "metadata").mkdir()
        lines = []
        for fvs in sets:
            meta, counts = export_scene(fvs, final, tmp)
            (tmp / "metadata" / f"{fvs.scene_id}.json").write_text(json.dumps(meta, indent=1))
            lines.append(str(final / "metadata" / f"{fvs.scene_id}.json"))
            res.counts[fvs.scene_id] = counts
            ch = choose_eval_views(fvs, n_context, n_target)
            index[fvs.scene_id] = None if ch is None else {"context": ch[0], "target": ch[1]}
        (tmp / "full_list.txt").write_text("\n".join(lines) + "\n")
        (tmp / "evaluation_index.json").write_text(json.dumps(index, indent=1))
        res.files += ["full_list.txt", "evaluation_index.json"] + \
            [f"metadata/{s.scene_id}.json" for s in sets]
    res.load_command = (f"python train.py --config configs/LVSM_scene_decoder_only.yaml "
                        f"training.dataset_path={final}/full_list.txt  # evaluation: "
                        f"inference.view_idx_file_path={final}/evaluation_index.json")
    return res
