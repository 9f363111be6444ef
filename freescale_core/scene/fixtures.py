"""Synthetic captures in other tools' formats, made from the procedural sample scene (tests,
``benchmarks/faults.py``).

* :func:`write_instant_ngp_scene`: an instant-ngp style ``transforms.json``: rotations
  printed to 6 decimals (orthonormal only to ~1e-6), OPENCV distortion parameters, no sparse
  points, ``aabb_scale``, per-frame ``sharpness``, optionally frames whose image is absent.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

__all__ = ["write_instant_ngp_scene"]


def write_instant_ngp_scene(sample_dir: str | Path, out_dir: str | Path, decimals: int = 6,
                            k1: float = 1e-3, n_absent: int = 1) -> Path:
    """Write ``out_dir`` (``images/`` + ``transforms.json``) from a sample scene folder."""
    import pycolmap

    from freescale_core.scene.io import load_scene
    from freescale_core.scene.io.nerfstudio import transforms_dict

    sample_dir, out = Path(sample_dir), Path(out_dir)
    sc = load_scene(sample_dir)
    out.mkdir(parents=True, exist_ok=True)
    shutil.copytree(sample_dir / "images", out / "images")
    cams = [pycolmap.Camera(model="OPENCV", width=int(sc.cameras.width[i]),
                            height=int(sc.cameras.height[i]),
                            params=np.array([sc.cameras.fx[i], sc.cameras.fy[i],
                                             sc.cameras.cx[i], sc.cameras.cy[i],
                                             k1, 0.0, 0.0, 0.0]))
            for i in range(len(sc))]
    meta = transforms_dict(list(sc.image_names), sc.cameras.world_from_cam, cams)
    for f in meta["frames"]:
        f["transform_matrix"] = np.round(np.asarray(f["transform_matrix"]), decimals).tolist()
        f["sharpness"] = 100.0
    # instant-ngp: x_ngp = x * scale + offset, box [0.5 - a/2, 0.5 + a/2]^3, a a power of 2
    half = 1.2 * float(np.abs(sc.cameras.centers).max())
    a = float(2 ** np.ceil(np.log2(2 * 0.33 * half)))
    meta.update(aabb_scale=int(a), scale=0.33, offset=[0.5, 0.5, 0.5])
    for k in range(n_absent):
        meta["frames"].append({"file_path": f"images/missing_{k:03d}.png",
                               "sharpness": 10.0,
                               "transform_matrix": meta["frames"][k]["transform_matrix"]})
    (out / "transforms.json").write_text(json.dumps(meta, indent=1))
    return out
