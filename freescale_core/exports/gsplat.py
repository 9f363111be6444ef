"""Export to gsplat: ``OUT/<scene>/ckpt.pt`` + ``gaussians.ply`` + ``cameras.npz``.

* ``ckpt.pt``: ``torch.save({"step": 0, "splats": {...}})``, the layout gsplat's
  ``examples/simple_trainer.py`` saves and loads (``--ckpt``): ``means [N, 3]``,
  ``scales [N, 3]`` (log), ``quats [N, 4]`` (wxyz, unnormalised), ``opacities [N]`` (logits),
  ``sh0 [N, 1, 3]``, ``shN [N, K-1, 3]`` (K = (deg+1)^2; ``[N, 0, 3]`` at degree 0), float32.
  Parameters are unactivated, as in the PLY.
* ``gaussians.ply``: the published 3DGS PLY (hard link).
* ``cameras.npz``: ``viewmats [C, 4, 4]`` float32 ``cam_from_world`` (OpenCV axes, what
  ``gsplat.rasterization`` takes), ``Ks [C, 3, 3]``, ``width [C]``, ``height [C]``,
  ``view_id [C]``, ``is_free [C]``, ``image_names [C]`` (``images/<name>`` written beside,
  captured views first in capture order, then the free views).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from freescale_core.errors import StoreError
from freescale_core.exports.common import (ExportResult, atomic_dir, frame_order, link_or_copy,
                                           scene_sets, write_png)


def splats_dict(g) -> dict:
    """gsplat's ``splats`` state dict (torch tensors) from :class:`Gaussians`."""
    import torch

    sh = np.asarray(g.sh, np.float32)
    return {"means": torch.from_numpy(np.ascontiguousarray(g.means, np.float32)),
            "scales": torch.from_numpy(np.ascontiguousarray(g.log_scales, np.float32)),
            "quats": torch.from_numpy(np.ascontiguousarray(g.quats_wxyz, np.float32)),
            "opacities": torch.from_numpy(np.ascontiguousarray(g.opacity_logits, np.float32)),
            "sh0": torch.from_numpy(np.ascontiguousarray(sh[:, :1])),
            "shN": torch.from_numpy(np.ascontiguousarray(sh[:, 1:]))}


def export_scene(fvs, out: Path) -> dict:
    import torch

    from freescale_core.geometry.cameras import invert_pose
    from freescale_core.scene.ply import read_ply

    ply = fvs.gaussians_ply
    if ply is None:
        raise StoreError(f"scene {fvs.scene_id!r}: {fvs.version_dir} has no gaussians.ply")
    g = read_ply(ply, scene_id=fvs.scene_id)
    torch.save({"step": 0, "splats": splats_dict(g)}, out / "ckpt.pt")
    link_or_copy(ply, out / "gaussians.ply")
    v = fvs.dataset_views()
    order = frame_order(fvs)
    cams = v.cameras.subset(order)
    names = []
    for k, r in enumerate(order):
        vid = int(v.view_id[r])
        if v.is_free[r]:
            name = f"images/{k:05d}_free_{vid:05d}.png"
            write_png(out / name, fvs.rgb(vid))
        else:
            name = f"images/{k:05d}_{Path(str(v.name[r])).name}"
            link_or_copy(fvs.image_path(vid), out / name)
        names.append(name)
    np.savez(out / "cameras.npz", viewmats=invert_pose(cams.world_from_cam).astype(np.float32),
             Ks=cams.K.astype(np.float32), width=cams.width, height=cams.height,
             view_id=v.view_id[order], is_free=v.is_free[order], image_names=np.array(names))
    return {"train": int((~v.is_free).sum()), "free": int(v.is_free.sum()), "gaussians": len(g)}


def export(store_root, out, scenes: list[str] | None = None,
           overwrite: bool = False) -> ExportResult:
    sets = scene_sets(store_root, scenes)
    final = Path(out).absolute()
    res = ExportResult("gsplat", final, [s.scene_id for s in sets])
    with atomic_dir(final, overwrite) as tmp:
        for fvs in sets:
            d = tmp / fvs.scene_id
            d.mkdir()
            res.counts[fvs.scene_id] = export_scene(fvs, d)
            res.files += [f"{fvs.scene_id}/ckpt.pt", f"{fvs.scene_id}/cameras.npz"]
    first = final / sets[0].scene_id
    res.load_command = (
        f"python -c \"import torch, numpy as np; s = torch.load('{first}/ckpt.pt')['splats']; "
        f"c = np.load('{first}/cameras.npz'); print({{k: v.shape for k, v in s.items()}}, "
        f"c['viewmats'].shape)\"  # then gsplat.rasterization(s['means'], "
        f"F.normalize(s['quats'], dim=-1), s['scales'].exp(), s['opacities'].sigmoid(), "
        f"torch.cat([s['sh0'], s['shN']], 1), viewmats, Ks, W, H, sh_degree=...)  or  "
        f"examples/simple_trainer.py default --ckpt {first}/ckpt.pt")
    return res
