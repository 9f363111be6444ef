"""A capture whose photos differ in exposure, from one whose photos agree: each image of a COLMAP
scene folder multiplied by a per-view gain, the model and points copied as they are.

    .venv/bin/python -m lab.paint_exposure SRC DST [--log-std 0.1] [--seed 0]
    .venv/bin/python -m lab.paint_exposure --sample 12 DST [--log-std 0.1]   # sample scene, 12 views
    .venv/bin/python -m lab.paint_exposure SRC DST --clean-split every8    # held-out views as shot

A hand-held auto-exposure camera gives each photo its own brightness; the sparse points keep
the colours they were given. The log-gains are drawn from N(0, log_std) per view (one gain for
R, G and B), re-centred on their mean, and written to ``DST/exposure_gains.json`` in image-name
order; pixels are rounded and clipped to 0..255. With ``--clean-split SPLIT`` the held-out
views of that split keep their photos (gain 1): the held-out PSNR then scores the scene's
colour, not how well a model guesses an unseen photo's exposure. Same arguments, same files.
DST is written into a temporary folder beside it and renamed into place at the end.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image



def paint(src: Path, dst: Path, log_std: float, seed: int,
          keep: set[str] = frozenset()) -> dict[str, float]:
    """Copy ``src`` to ``dst`` with every image times its view's gain; returns name -> log-gain.
    Images named in ``keep`` are copied as they are (log-gain 0, outside the re-centring)."""
    src, dst = Path(src), Path(dst)
    names = sorted(p.name for p in (src / "images").iterdir() if p.is_file())
    if not names:
        raise ValueError(f"{src}: no images in {src / 'images'}")
    g = np.random.default_rng(seed).normal(0.0, log_std, len(names))
    painted = np.array([n not in keep for n in names])
    if painted.any():
        g -= g[painted].mean()
    g[~painted] = 0.0
    tmp = Path(tempfile.mkdtemp(prefix=f".{dst.name}.", dir=dst.parent))
    try:
        for item in src.iterdir():
            if item.name != "images":
                (shutil.copytree if item.is_dir() else shutil.copy2)(item, tmp / item.name)
        (tmp / "images").mkdir()
        for name, lg in zip(names, g):
            img = np.asarray(Image.open(src / "images" / name).convert("RGB"), np.float64)
            out = np.clip(np.round(img * np.exp(lg)), 0, 255).astype(np.uint8)
            Image.fromarray(out).save(tmp / "images" / name)
        gains = {n: round(float(v), 6) for n, v in zip(names, g)}
        (tmp / "exposure_gains.json").write_text(json.dumps(
            {"log_std": log_std, "seed": seed, "log_gain": gains}, indent=1))
        if dst.exists():
            shutil.rmtree(dst)
        tmp.rename(dst)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return gains


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("paths", nargs="+", help="SRC DST, or DST with --sample")
    ap.add_argument("--sample", type=int, default=None, metavar="N_VIEWS",
                    help="paint the embedded sample scene written with this many views")
    ap.add_argument("--log-std", type=float, default=0.1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--clean-split", choices=["ood", "every8"], default=None,
                    help="leave this split's held-out views unpainted")
    a = ap.parse_args(argv)
    if a.sample is None:
        src, dst = map(Path, a.paths)
        return _paint_and_report(src, dst, a)
    from freescale_core.scene.sample import write_sample_scene

    (dst,) = map(Path, a.paths)
    with tempfile.TemporaryDirectory() as tmp:  # the unpainted sample scene is not kept
        src = write_sample_scene(Path(tmp) / "sample", n_views=a.sample)
        return _paint_and_report(src, dst, a)


def _paint_and_report(src: Path, dst: Path, a) -> int:
    keep: set[str] = set()
    if a.clean_split:
        from freescale_core.scene.io import load_scene

        sc = load_scene(src)
        keep = {sc.image_names[int(i)] for i in sc.split(a.clean_split)[1]}
    g = paint(src, dst, a.log_std, a.seed, keep)
    v = np.array(list(g.values()))
    print(f"{dst}: {len(v)} views, log-gain std {v.std():.3f}, range {v.max() - v.min():.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
