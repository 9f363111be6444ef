"""Noisy COLMAP poses: the pose-noise stability families, procedural
(:mod:`freescale_core.eval.scenes`) and real (:mod:`freescale_core.eval.real_variants`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def perturb_colmap_poses(images_txt: Path, rot_deg: float, trans_frac: float,
                         seed: int, only: set[str] | None = None) -> None:
    """Rewrite the poses of a COLMAP ``images.txt`` with noise (``scene.json`` keeps the
    truth): a random-axis rotation of N(0, rot_deg) degrees about each camera centre, and the
    centre moved by N(0, trans_frac x path length) per axis (path length over every image,
    in file order). ``only``: perturb the images of these names only (the others keep their
    poses; the random draws are made for every image either way)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng([seed, 16])
    lines = images_txt.read_text().splitlines()
    rows = [i for i, ln in enumerate(lines) if not ln.startswith("#")][::2]
    poses = []
    for i in rows:
        f = lines[i].split()
        q = np.array([float(x) for x in f[1:5]])  # qw qx qy qz (cam_from_world)
        t = np.array([float(x) for x in f[5:8]])
        R = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
        poses.append((f, R, t, -R.T @ t))
    centres = np.array([p[3] for p in poses])
    length = float(np.linalg.norm(np.diff(centres, axis=0), axis=1).sum()) if len(centres) > 1 \
        else 1.0
    for i, (f, R, t, c) in zip(rows, poses):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        dR = Rotation.from_rotvec(axis * np.deg2rad(rng.normal(0.0, rot_deg))).as_matrix()
        R2 = dR @ R  # rotate the camera about its own centre
        c2 = c + rng.normal(0.0, trans_frac * length, 3)
        t2 = -R2 @ c2
        if only is not None and f[9] not in only:
            continue
        x, y, z, w = Rotation.from_matrix(R2).as_quat()
        lines[i] = " ".join([f[0], *(repr(float(v)) for v in (w, x, y, z, *t2)), *f[8:]])
    images_txt.write_text("\n".join(lines) + "\n")
