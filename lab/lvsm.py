"""Does training LVSM on FreeScale free views help? Arms x evaluation regimes on held-out scenes.

Scenes: procedural family scenes (``freescale_core.scene.family``: random layouts, mixed
photo/procedural textures, any capture path); training scenes and held-out scenes use
disjoint seeds. Free views: ``generate-dataset`` (``python -m flows.cli run ... --preset
fast``) on each training scene's capture only; rows of ``views.parquet`` with disposition
``free_view``, pixels from ``arrays.zarr/freeviews/rgb`` (cropped to ``freeviews/size``), the
view graph from ``view_graph.parquet``.

Arms (same seeds, model, steps, batch):

* ``A``   : sampler target_mode "between", captured views only (LVSM's default);
* ``A'``  : "extrapolate", captured only;
* ``B22`` : A' + engine free views through the view-graph sampler, free views = 22% of each
  scene's views (the paper's ratio; a fixed random subset of the engine's free views);
* ``Ball``: A' + all the engine's free views through the view-graph sampler;
* ``D``   : A' + the same free views as B22, drawn at random (``random_free``: no graph);
* ``C``   : ceiling: B22 with the oracle's true images at the free views' poses.
* ``B_raw``  : B22's recipe on a store made with ``freeview.rectifier.backend=fixer``, its raw
  renders (``freeviews/rgb_render``: rectifier none);
* ``B_fixed``: the same views, the fixer's images (``freeviews/rgb``), the loss weighted per
  pixel by the fixer's confidence (``freeviews/confidence``; ``confidence_weight``).
  The shipped fixer was trained on procedural seeds 100-105 and the shared real scenes; the
  scenes here use seeds 1000+ (training) and 5000+ (held out), so it never saw them.

Evaluation (``freescale_core.eval.lvsm_eval``): small motion (target between inputs), large
motion along the path (extrapolation), off-path (poses never visited; oracle truth), with the
copy-nearest-input and mean-of-inputs baselines. PSNR / SSIM mean +- std over seeds.

    python -m lab.lvsm --quick            # 2+2 scenes, 60 steps, ~5 min
    python -m lab.lvsm                    # 'medium': 6+3 scenes, 300 steps (resumable)

Everything (scenes, store, runs, results.json) lives under ``--out`` (default: a folder in
/tmp); finished runs are reused when the script is started again with the same settings.
"""

from __future__ import annotations

import os
import sys


import argparse
import json
import subprocess
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]

from freescale_core.downstream.lvsm.data import (
    SceneTensors,
    add_views,
    load_sample_scene,
)
from freescale_core.downstream.lvsm.sampler import SceneViews
from freescale_core.downstream.lvsm.train import train_lvsm
from freescale_core.eval.lvsm_eval import (
    METHODS,
    REGIMES,
    build_examples,
    evaluate,
    load_eval_scene,
)
from freescale_core.scene.family import write_family
from freescale_core.scene.sample import SampleWorld
from freescale_core.store.layout import world_from_cam_column
from freescale_core.store.store import Store, write_json_atomic
from schemas.lvsm import LVSMEvalConfig, LVSMSamplerConfig, TrainLVSMConfig
from schemas.scene_family import SceneFamilyConfig

ARMS = ("A", "A'", "B22", "Ball", "D", "C", "B_raw", "B_fixed")
FIXER_ARMS = ("B_raw", "B_fixed")
PAPER_FREE_RATIO = 0.22

PROFILES = {
    "quick": dict(n_train=2, n_eval=2, n_views=24, cap_w=128, cap_h=96, W=64, H=48,
                  steps=60, batch=4, warmup=10, d_model=64, n_layers=2, n_heads=4,
                  n_per_scene=4, seeds=(0, 1, 2), lr=1e-3, evals=1),
    "medium": dict(n_train=6, n_eval=3, n_views=24, cap_w=128, cap_h=96, W=64, H=48,
                   steps=300, batch=8, warmup=30, d_model=64, n_layers=2, n_heads=4,
                   n_per_scene=6, seeds=(0, 1, 2), lr=1e-3, evals=3),
}


# --------------------------------------------------------------------------- scenes + store
def make_scenes(out: Path, p: dict) -> tuple[list[Path], list[Path]]:
    fam = SceneFamilyConfig(layout="random", textures="mixed", path="any")
    kw = dict(family=fam, n_views=p["n_views"], width=p["cap_w"], height=p["cap_h"],
              n_points=2000)
    sets = []
    for name, n, seed in (("train", p["n_train"], 1000), ("eval", p["n_eval"], 5000)):
        d = out / "scenes" / name
        dirs = [d / f"scene_{k:04d}" for k in range(n)]
        if not all((x / "scene.json").is_file() for x in dirs):
            dirs = write_family(d, n, seed=seed, **kw)
        sets.append(dirs)
    return sets[0], sets[1]


def run_engine(train_dirs: list[Path], store: Path, extra: tuple[str, ...] = ()) -> float:
    """generate-dataset (preset fast, + ``extra`` CLI args) on the training captures; seconds
    (0 when cached)."""
    st = Store(store)
    if store.exists() and all(st.read_status(d.name).get("status") == "ok" for d in train_dirs):
        return 0.0
    t = time.perf_counter()
    cmd = [sys.executable, "-m", "flows.cli", "run", *map(str, train_dirs), "--store",
           str(store), "--preset", "fast", *extra]
    # a loaded machine starts Prefect's temporary API server slowly (default wait: 20 s)
    env = {**os.environ, "PYTHONPATH": str(ROOT),
           "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "300"}
    for _attempt in range(2):  # the store resumes finished scenes on the second attempt
        r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env=env)
        if r.returncode == 0:
            break
    if r.returncode != 0:
        sys.stderr.write(r.stdout[-3000:] + r.stderr[-3000:])
        raise SystemExit(f"generate-dataset failed (exit {r.returncode})")
    return time.perf_counter() - t


def read_free_views(store: Path, scene_dir: Path, base: SceneTensors,
                    images: str = "freeviews/rgb") -> dict:
    """The engine's free views of one scene and its view graph in SceneTensors ids.

    ``images``: the array to read the pixels from (``freeviews/rgb_render`` for the raw
    renders of a fixer store); ``conf`` holds ``freeviews/confidence`` when the store has it.
    """
    st = Store(store)
    sid = scene_dir.name
    views = st.views(sid).to_pydict()
    tab = st.views(sid)
    c2w_all = world_from_cam_column(tab)  # [V, 4, 4]
    world = SampleWorld.load(scene_dir)
    name_to_cap = {n: i for i, n in enumerate(world.image_names)}
    T = base.views.n_views
    new_id: dict[int, int] = {}
    for vid, kind, name in zip(views["view_id"], views["kind"], views["name"]):
        if kind == "train":
            if name not in name_to_cap:
                raise ValueError(f"scene {sid!r}: store view {name!r} is not in the capture")
            new_id[int(vid)] = name_to_cap[name]
    arr = st.arrays(sid)
    rows = [i for i, d in enumerate(views["disposition"])
            if d == "free_view" and views["free_index"][i] >= 0]
    rgb, K, c2w, vids, gt, conf = [], [], [], [], [], []
    if rows:
        sizes = np.asarray(arr["freeviews/size"][:])
        allrgb = arr[images]
        allconf = arr["freeviews/confidence"] if "freeviews/confidence" in arr else None
        for i in rows:
            fi = int(views["free_index"][i])
            h, w = (int(v) for v in sizes[fi])
            rgb.append(np.asarray(allrgb[fi])[:h, :w])
            if allconf is not None:
                conf.append(np.asarray(allconf[fi])[:h, :w])
            K.append([views[c][i] for c in ("fx", "fy", "cx", "cy")])
            c2w.append(c2w_all[i])
            vids.append(int(views["view_id"][i]))
            gt.append(views.get("gt_psnr", [np.nan] * len(rows))[i])
    g = st.view_graph(sid).to_pydict()
    return dict(rgb=rgb, K=np.asarray(K, np.float64).reshape(-1, 4),
                c2w=np.asarray(c2w, np.float64).reshape(-1, 4, 4), view_ids=vids,
                train_id=new_id, n_captured=T, gt_psnr=gt, conf=conf or None,
                graph=(np.asarray(g["src"], np.int64), np.asarray(g["dst"], np.int64),
                       np.asarray(g["wiou"], np.float64)), world=world)


def with_free(base: SceneTensors, fv: dict, keep: np.ndarray, oracle: bool,
              confidence: bool = False) -> SceneTensors:
    """``base`` + the free views ``keep`` (indices into fv lists), graph remapped; with
    ``confidence`` their per-pixel confidence (``fv["conf"]``) goes along."""
    if len(keep) == 0:
        return base
    T = fv["n_captured"]
    ids = dict(fv["train_id"])
    for j, k in enumerate(keep):
        ids[fv["view_ids"][k]] = T + j
    src, dst, w = fv["graph"]
    ok = np.array([s in ids and d in ids for s, d in zip(src.tolist(), dst.tolist())], bool)
    edges = (np.array([ids[s] for s in src[ok].tolist()], np.int64),
             np.array([ids[d] for d in dst[ok].tolist()], np.int64), w[ok])
    if oracle:
        world = fv["world"]
        rgb = []
        for k in keep:
            h, wd = fv["rgb"][k].shape[:2]
            fx, fy, cx, cy = fv["K"][k]
            rgb.append(world.render(fv["c2w"][k], fx, fy, cx, cy, wd, h)[0])
    else:
        rgb = [fv["rgb"][k] for k in keep]
    out = base
    # views differ in size only if the engine stored mixed sizes: add them one by one
    for j, k in enumerate(keep):
        cf = fv["conf"][k][None] if confidence else None
        out = add_views(out, rgb[j][None], fv["K"][k][None], fv["c2w"][k][None], confidence=cf)
    return SceneTensors(SceneViews(base.scene_id, out.views.is_free, out.views.frame_index, edges),
                        out.images, out.K, out.world_from_cam, out.confidence)


# --------------------------------------------------------------------------- arms
def arm_scenes(arm: str, bases: list[SceneTensors], fvs: list[dict], seed: int = 0
               ) -> list[SceneTensors]:
    if arm in ("A", "A'"):
        return bases
    out = []
    for si, (b, fv) in enumerate(zip(bases, fvs)):
        m = len(fv["rgb"])
        if arm == "Ball":
            keep = np.arange(m)
        else:  # the paper's ratio: free / (captured + free) = 22%
            n22 = int(round(PAPER_FREE_RATIO / (1 - PAPER_FREE_RATIO) * b.views.n_views))
            keep = np.sort(np.random.default_rng([seed, si, 22]).permutation(m)[:min(m, n22)])
        out.append(with_free(b, fv, keep, oracle=(arm == "C"),
                             confidence=(arm == "B_fixed")))
    return out


def arm_sampler(arm: str, p: dict) -> LVSMSamplerConfig:
    base = dict(n_input=4, n_target=1, reference_length=None, frame_dist=(6, 12),
                warmup_frame_dist=(5, 8), warmup_steps=max(1, p["steps"] // 3),
                graph_prob=0.5)
    if arm == "A":
        return LVSMSamplerConfig(**base, target_mode="between", use_free_views=False)
    if arm == "A'":
        return LVSMSamplerConfig(**base, target_mode="extrapolate", use_free_views=False)
    return LVSMSamplerConfig(**base, target_mode="extrapolate", use_free_views=True,
                             random_free=(arm == "D"))


def _vs_oracle(fv: dict, _arm: str) -> np.ndarray:
    """PSNR (dB) of each free view's pixels against the oracle render at its pose."""
    out = []
    for k, im in enumerate(fv["rgb"]):
        h, w = im.shape[:2]
        fx_, fy, cx, cy = fv["K"][k]
        gt = fv["world"].render(fv["c2w"][k], fx_, fy, cx, cy, w, h)[0]
        mse = np.mean((im.astype(np.float64) / 255 - np.asarray(gt, np.float64)
                       / (255 if np.asarray(gt).dtype == np.uint8 else 1)) ** 2)
        out.append(-10 * np.log10(max(mse, 1e-10)))
    return np.asarray(out, float)


def fmt(vals: list[float], nd: int = 2) -> str:
    v = np.asarray(vals, float)
    return f"{v.mean():.{nd}f} ± {v.std():.{nd}f}" if len(v) > 1 else f"{v.mean():.{nd}f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="tiny configuration (< 5 min)")
    ap.add_argument("--profile", choices=sorted(PROFILES), default=None)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--seeds", type=int, nargs="*", default=None)
    ap.add_argument("--arms", nargs="*", default=list(ARMS))
    ap.add_argument("--threads", type=int, default=1, help="torch threads (2 shared cores)")
    ap.add_argument("--d-model", type=int, default=None, help="token width (profile: 64)")
    ap.add_argument("--n-layers", type=int, default=None, help="transformer blocks (profile: 2)")
    ap.add_argument("--n-heads", type=int, default=None, help="attention heads (profile: 4)")
    ap.add_argument("--n-train", type=int, default=None,
                    help="training scenes (profile: 6 medium, 2 quick)")
    ap.add_argument("--fixer-store", action="store_true",
                    help="free views of every arm from the fixer store (implied by B_raw / "
                    "B_fixed; B22 = B_raw, C at the same poses)")
    ap.add_argument("--train-scenes", type=int, nargs="*", default=None,
                    help="indices of the profile's training scenes to use (default: all)")
    ap.add_argument("--evals", type=int, default=None,
                    help="held-out evaluations per run (learning curve points; profile: 3)")
    a = ap.parse_args()
    prof = a.profile or ("quick" if a.quick else "medium")
    p = dict(PROFILES[prof])
    if a.steps:
        p["steps"] = a.steps
    if a.seeds:
        p["seeds"] = tuple(a.seeds)
    if a.n_train:
        p["n_train"] = a.n_train
    size0 = (p["d_model"], p["n_layers"], p["n_heads"])
    for k in ("d_model", "n_layers", "n_heads", "evals"):
        if getattr(a, k) is not None:
            p[k] = getattr(a, k)
    # runs of another model size get their own keys and folders (the profile's keep theirs)
    size_tag = "" if (p["d_model"], p["n_layers"], p["n_heads"]) == size0 else \
        f"_d{p['d_model']}L{p['n_layers']}h{p['n_heads']}"
    if p["n_train"] != PROFILES[prof]["n_train"]:
        size_tag += f"_t{p['n_train']}"
    out = a.out or Path(f"/tmp/freescale-lvsm-{prof}")
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(a.threads)
    t0 = time.perf_counter()

    train_dirs, eval_dirs = make_scenes(out, p)
    if a.train_scenes:
        train_dirs = [train_dirs[i] for i in a.train_scenes]
        size_tag += "_s" + "-".join(map(str, a.train_scenes))
    t_scenes = time.perf_counter() - t0
    bases = [load_sample_scene(d, p["W"], p["H"]) for d in train_dirs]
    fx = {}  # B_raw / B_fixed: a store made with the fixer (raw renders, fixed images + conf)
    if a.fixer_store or any(arm in FIXER_ARMS for arm in a.arms):
        # one engine run: its raw renders are today's free views (rectifier none), so every
        # free-view arm (B22 = B_raw, C, B_fixed) uses the same poses
        store = out / "store_fixer"
        t_engine = run_engine(train_dirs, store, ("--set", "freeview.rectifier.backend=fixer"))
        fx["B_raw"] = [read_free_views(store, d, b, "freeviews/rgb_render")
                       for d, b in zip(train_dirs, bases)]
        fx["B_fixed"] = [read_free_views(store, d, b) for d, b in zip(train_dirs, bases)]
        fvs = fx["B_raw"]
        fixed_psnr = [_vs_oracle(f, "B_fixed") for f in fx["B_fixed"]]
        raw_psnr = [_vs_oracle(f, "B_raw") for f in fx["B_raw"]]
        print(f"fixer store: free views vs oracle (mean over views) raw "
              f"{np.nanmean(np.concatenate(raw_psnr)):.2f} dB, fixed "
              f"{np.nanmean(np.concatenate(fixed_psnr)):.2f} dB")
    elif all(arm in ("A", "A'") for arm in a.arms):  # captured views only: no engine run
        t_engine, fvs = 0.0, [dict(rgb=[], gt_psnr=[]) for _ in train_dirs]
    else:
        store = out / "store"
        t_engine = run_engine(train_dirs, store)
        fvs = [read_free_views(store, d, b) for d, b in zip(train_dirs, bases)]
    n_free = [len(f["rgb"]) for f in fvs]
    gt = [x for f in fvs for x in f["gt_psnr"] if x is not None and np.isfinite(x)]
    print(f"profile {prof}: {len(train_dirs)} training scenes x {p['n_views']} views, "
          f"{len(eval_dirs)} held-out; scenes {t_scenes:.0f} s, generate-dataset "
          f"{t_engine:.0f} s; free views per scene {n_free}"
          + (f", their PSNR vs oracle {np.mean(gt):.2f} dB" if gt else ""))

    eval_scenes = [load_eval_scene(d, p["W"], p["H"]) for d in eval_dirs]
    ecfg = LVSMEvalConfig(n_input=4, n_per_scene=p["n_per_scene"], small_span=6,
                          large_span=6, extrap_frames=(3, 6), offpath_span=6)
    examples = build_examples(eval_scenes, ecfg)
    base_scores = evaluate(None, examples)

    res_path = out / "results.json"
    results = json.loads(res_path.read_text()) if res_path.is_file() else {}
    bad = [arm for arm in a.arms if arm not in ARMS]
    if bad:
        raise SystemExit(f"unknown arm(s) {bad}; choose from {ARMS}")
    for seed in p["seeds"]:  # seeds outer: a cut-short run still has every arm at seed 0
        for arm in a.arms:
            key = f"{arm}|{seed}|{p['steps']}{size_tag.replace('_', '|')}"
            if key in results:
                continue
            scenes = arm_scenes(arm, bases, fx.get(arm, fvs))
            cfg = TrainLVSMConfig(
                steps=p["steps"], batch_size=p["batch"], lr=p["lr"], warmup_steps=p["warmup"],
                eval_every=max(1, p["steps"] // p["evals"]),
                ckpt_every=max(1, p["steps"] // 4),
                log_every=max(1, p["steps"] // 4), eval_samples=8,
                confidence_weight=(arm == "B_fixed"),
                model_overrides=dict(d_model=p["d_model"], n_layers=p["n_layers"],
                                     n_heads=p["n_heads"], image_size=p["W"]),
                sampler=arm_sampler(arm, p))
            t, c = time.perf_counter(), time.process_time()
            run_dir = out / "runs" / f"{arm.replace(chr(39), 'p')}_s{seed}_n{p['steps']}{size_tag}"
            r = train_lvsm(scenes, cfg, seed=seed, out_dir=run_dir,
                           eval_scenes=[e.tensors for e in eval_scenes], log=None)
            scores = evaluate(r.model, examples)
            tr = r.history["train"]
            results[key] = dict(arm=arm, seed=seed, steps=p["steps"], d_model=p["d_model"],
                                n_layers=p["n_layers"], n_heads=p["n_heads"],
                                n_params=sum(x.numel() for x in r.model.parameters()),
                                cpu_seconds=time.process_time() - c,
                                seconds=time.perf_counter() - t,
                                final_train_loss=float(np.mean([x["loss"] for x in tr[-10:]])),
                                free_target_share=float(
                                    sum(x["n_free_targets"] for x in tr) / (len(tr) * p["batch"])),
                                heldout=r.history["eval"],  # learning curve: step, loss, psnr
                                scores={k: v["model"] for k, v in scores.items()})
            write_json_atomic(res_path, results)
            print(f"  {arm:5s} seed {seed}: {results[key]['seconds']:.0f} s, "
                  + ", ".join(f"{k} {v['model']['psnr']:.2f}" for k, v in scores.items()),
                  flush=True)

    # ---- table
    print(f"\nPSNR (dB) / SSIM on held-out scenes, mean ± std over seeds {list(p['seeds'])}; "
          f"{p['steps']} steps x batch {p['batch']}, d={p['d_model']} L={p['n_layers']}, "
          f"{p['W']}x{p['H']} px; examples per regime: "
          + ", ".join(f"{r} {len(examples[r])}" for r in REGIMES))
    head = "| arm | " + " | ".join(f"{r} PSNR | {r} SSIM" for r in REGIMES) + " | free tgt share |"
    print(head)
    print("|" + "---|" * (2 * len(REGIMES) + 2))
    for arm in a.arms:
        rows = [v for v in results.values() if v["arm"] == arm and v["steps"] == p["steps"]
                and v["seed"] in p["seeds"]
                and v.get("d_model", size0[0]) == p["d_model"]
                and v.get("n_layers", size0[1]) == p["n_layers"]
                and v.get("n_heads", size0[2]) == p["n_heads"]]
        if not rows:
            continue
        cells = []
        for r in REGIMES:
            cells.append(fmt([x["scores"][r]["psnr"] for x in rows]))
            cells.append(fmt([x["scores"][r]["ssim"] for x in rows], 3))
        share = np.mean([x["free_target_share"] for x in rows])
        print(f"| {arm} | " + " | ".join(cells) + f" | {share:.2f} |")
    for m in METHODS[1:]:
        cells = []
        for r in REGIMES:
            cells += [f"{base_scores[r][m]['psnr']:.2f}", f"{base_scores[r][m]['ssim']:.3f}"]
        print(f"| {m} | " + " | ".join(cells) + " | - |")
    print(f"\ntotal {time.perf_counter() - t0:.0f} s; results: {res_path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
