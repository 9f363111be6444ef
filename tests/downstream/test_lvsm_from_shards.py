"""train-lvsm from packed shards (freescale_core.downstream.lvsm.from_shards, flows/train_lvsm.py,
``freescale train-lvsm``): shards -> scenes, the held-out split, files written, a run killed
with SIGKILL resumes to the uninterrupted result, the Prefect flow and the CLI."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

# Prefect binds its console log handler to sys.stderr when first imported: import it here, not
# first inside a test that captures (and then closes) stderr
import flows.train_lvsm  # noqa: F401
from freescale_core.downstream.lvsm.from_shards import (
    RunExistsError,
    load_shard_scenes,
    split_heldout,
    train_from_shards,
)
from schemas.lvsm import TrainLVSMShardsConfig

REPO = Path(__file__).resolve().parents[2]
R = 16  # shard resolution = model image size (patch 8: 2 x 2 tokens)
N_VIEWS, N_FREE = 12, 4

# a tiny run: 20 steps, checkpoints every 5, held-out every 10
TINY = {"train": {"steps": 20, "batch_size": 2, "lr": 2e-3, "warmup_steps": 3,
                  "eval_every": 10, "ckpt_every": 5, "log_every": 5, "eval_samples": 4,
                  "model_overrides": {"d_model": 32, "n_layers": 1, "n_heads": 2,
                                      "image_size": R},
                  "sampler": {"n_input": 2, "n_target": 1, "warmup_steps": 10,
                              "reference_length": None, "frame_dist": [3, 6],
                              "warmup_frame_dist": [2, 4]}}}
TINY_SET = ["--set", "train.batch_size=2", "--set", "train.lr=0.002",
            "--set", "train.warmup_steps=3", "--set", "train.eval_every=10",
            "--set", "train.ckpt_every=5", "--set", "train.log_every=5",
            "--set", "train.eval_samples=4",
            "--set", ('train.model_overrides={"d_model": 32, "n_layers": 1, "n_heads": 2, '
                      f'"image_size": {R}}}'),
            "--set", "train.sampler.n_input=2", "--set", "train.sampler.n_target=1",
            "--set", "train.sampler.warmup_steps=10",
            "--set", "train.sampler.reference_length=null",
            "--set", "train.sampler.frame_dist=[3,6]",
            "--set", "train.sampler.warmup_frame_dist=[2,4]"]


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def write_tiny_shards(out: Path, n_scenes: int = 3) -> Path:
    """Shards in the ``freescale shards pack`` format, made without the engine (seconds): sample
    scenes' captured views plus ``N_FREE`` oracle renders near captured cameras as free views,
    linked to their source view in the graph; captured frames chained."""
    from freescale_core.scene.sample import SampleWorld, write_sample_scene
    from freescale_core.scene.scene import read_rgb
    from freescale_core.store import shards as S
    from freescale_core.store.store import write_parquet_atomic

    packed = []
    for k in range(n_scenes):
        d = write_sample_scene(out.parent / "scenes" / f"scene_{k:02d}", n_views=N_VIEWS,
                               width=32, height=24, seed=k, n_points=50)
        world = SampleWorld.load(d)
        c = world.cameras
        imgs, K, c2w = [], [], []
        for i, name in enumerate(world.image_names):
            im, kk = S.resize_crop(read_rgb(d / "images" / name, d.name),
                                   np.array([c.fx[i], c.fy[i], c.cx[i], c.cy[i]]), R)
            imgs.append(im), K.append(kk), c2w.append(c.world_from_cam[i])
        src_views = np.linspace(1, N_VIEWS - 2, N_FREE).astype(int)
        for i in src_views:  # a free view: the capture camera moved 0.1 m sideways
            T = np.array(c.world_from_cam[i], np.float64)
            T[:3, 3] += 0.1 * T[:3, 0]
            rgb = world.render(T, c.fx[i], c.fy[i], c.cx[i], c.cy[i], 32, 24)[0]
            im, kk = S.resize_crop(rgb, np.array([c.fx[i], c.fy[i], c.cx[i], c.cy[i]]), R)
            imgs.append(im), K.append(kk), c2w.append(T)
        V = N_VIEWS + N_FREE
        is_free = np.arange(V) >= N_VIEWS
        src = np.concatenate([np.arange(N_VIEWS - 1), src_views])
        dst = np.concatenate([np.arange(1, N_VIEWS), np.arange(N_VIEWS, V)])
        packed.append(S.PackedScene(
            scene_id=d.name, images=np.stack(imgs), fxfycxcy=np.stack(K).astype(np.float32),
            world_from_cam=np.stack(c2w), is_free=is_free,
            frame_index=np.where(is_free, -1, np.arange(V)), view_id=np.arange(V),
            mode=np.where(is_free, 1, 0).astype(np.int8), score_f=np.ones(V, np.float32),
            brisque=np.full(V, np.nan, np.float32), orig_size=np.tile([24, 32], (V, 1)),
            edges=(src, dst, np.full(len(src), 0.6, np.float32))))
    (out / "shards").mkdir(parents=True)
    recs = S.write_shard(out / "shards" / "000000.zarr", packed, R)
    rows = [dict(shard="000000", shard_path="shards/000000.zarr", scene_id=p.scene_id,
                 scene_index=k, view_start=r["view_start"], n_views=r["n_views"],
                 n_train=N_VIEWS, n_free=N_FREE, edge_start=r["edge_start"],
                 n_edges=r["n_edges"], resolution=R, shard_views=n_scenes * len(p),
                 shard_bytes=0, source_store="", source_version="v1", config_hash="",
                 engine_version="", scene_sha256=p.sha256(),
                 shard_sha256=S.shard_sha256(out / "shards" / "000000.zarr"), packed_at="")
            for k, (p, r) in enumerate(zip(packed, recs))]
    write_parquet_atomic(out / "manifest.parquet", S._rows_table(rows))
    return out


@pytest.fixture(scope="module")
def shards(tmp_path_factory) -> Path:
    return write_tiny_shards(tmp_path_factory.mktemp("lvsm_shards") / "shards")


def _cfg(**over) -> TrainLVSMShardsConfig:
    return TrainLVSMShardsConfig.model_validate({**TINY, **over})


def test_shard_scenes_and_heldout_split(shards):
    scenes = load_shard_scenes(shards)
    assert [s.scene_id for s in scenes] == ["scene_00", "scene_01", "scene_02"]
    s = scenes[0]
    assert s.images.shape == (N_VIEWS + N_FREE, 3, R, R) and s.images.max() <= 1
    assert int(s.views.is_free.sum()) == N_FREE
    assert len(s.views.edges[0]) == N_VIEWS - 1 + N_FREE
    assert load_shard_scenes(shards, ["scene_01"], image_size=8)[0].images.shape[-1] == 8

    train, held, split = split_heldout(scenes, _cfg())  # default: the last scene by id
    assert [t.scene_id for t in train] == ["scene_00", "scene_01"]
    assert [h.scene_id for h in held] == ["scene_02"] and not held[0].views.is_free.any()
    assert split["heldout_tail"] == 0

    # one scene: the last 30% of its capture is held out as views, the rest trains
    train, held, split = split_heldout(scenes[:1], _cfg(min_heldout_frames=3))
    assert split_heldout(scenes[:1], _cfg())[1] == []  # 4 frames: shorter than 6, not held out
    n_tail = round(0.3 * N_VIEWS)
    assert held[0].scene_id == "scene_00#tail" and held[0].views.n_views == n_tail
    assert split["heldout_views"]["scene_00"] == list(range(N_VIEWS - n_tail, N_VIEWS))
    assert train[0].views.n_views == N_VIEWS + N_FREE - n_tail
    assert int(train[0].views.frame_index.max()) == N_VIEWS - n_tail - 1
    src, dst, _ = train[0].views.edges
    assert max(src.max(), dst.max()) < train[0].views.n_views
    with pytest.raises(ValueError, match="not in the shards"):
        split_heldout(scenes, _cfg(heldout_scenes=["nope"]))


def _state(out: Path) -> dict:
    return torch.load(out / "ckpt" / "last.pt", map_location="cpu", weights_only=False)


def test_train_files_and_sigkill_resume_equals_uninterrupted(shards, tmp_path):
    full = tmp_path / "full"
    m = train_from_shards(shards, full, _cfg(), seed=3, log=None)
    for f in ("ckpt/last.pt", "history.json", "loss.png", "metrics.json", "split.json"):
        assert (full / f).is_file(), f
    assert (full / "loss.png").read_bytes()[:4] == b"\x89PNG"
    assert m["steps"] == 20 and m["resumed_from"] == 0 and m["heldout_scenes"] == ["scene_02"]
    assert [r["step"] for r in json.loads((full / "history.json").read_text())["eval"]] == [10, 20]
    assert np.isfinite(m["heldout_psnr"]) and m["it_s"] > 0 and m["n_free_train"] == 2 * N_FREE

    # the same run, killed with SIGKILL after step 13 (last checkpoint: step 10), then resumed
    cut = tmp_path / "cut"
    code = (
        "import os, signal, sys, torch\n"
        "torch.set_num_threads(1)\n"
        "from freescale_core.downstream.lvsm.from_shards import train_from_shards\n"
        "from schemas.lvsm import TrainLVSMShardsConfig\n"
        "def cb(step, rec):\n"
        "    if step == 13:\n"
        "        os.kill(os.getpid(), signal.SIGKILL)\n"
        f"train_from_shards({str(shards)!r}, {str(cut)!r}, "
        f"TrainLVSMShardsConfig.model_validate({TINY!r}), seed=3, log=None, callback=cb)\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=300, check=False)
    assert r.returncode == -9, r.stderr[-2000:]
    assert _state(cut)["step"] == 10 and not (cut / "metrics.json").exists()
    with pytest.raises(RunExistsError):
        train_from_shards(shards, cut, _cfg(), seed=3, log=None)
    m2 = train_from_shards(shards, cut, _cfg(), seed=3, log=None, resume=True)
    assert m2["resumed_from"] == 10
    a, b = _state(full), _state(cut)
    for k, v in a["model"].items():
        assert torch.equal(v, b["model"][k]), k
    strip = lambda h: [{k: v for k, v in x.items() if k != "it_s"} for x in h]  # timing dropped
    assert strip(a["history"]["train"]) == strip(b["history"]["train"])
    assert a["history"]["eval"] == b["history"]["eval"]
    for k in ("final_train_loss", "heldout_loss", "heldout_psnr"):
        assert m[k] == m2[k], k


def test_resume_refuses_other_shards_split_or_manifest(shards, tmp_path):
    """A resumed run on another shards folder (a newly held-out scene would be trained on),
    another split or a re-packed manifest is refused; split.json is left as it was."""
    import shutil

    cfg = _cfg()
    cfg.train.steps = 5
    out = tmp_path / "run"
    train_from_shards(shards, out, cfg, seed=0, log=None)
    split0 = (out / "split.json").read_bytes()
    other = tmp_path / "other" / "shards"
    shutil.copytree(shards, other)
    with pytest.raises(RunExistsError, match="other data: shards"):
        train_from_shards(other, out, cfg, seed=0, log=None, resume=True)
    moved = _cfg(heldout_scenes=["scene_00"])
    moved.train.steps = 5
    with pytest.raises(RunExistsError, match="heldout_scenes differ"):
        train_from_shards(shards, out, moved, seed=0, log=None, resume=True)
    import pyarrow.parquet as pq

    m = pq.read_table(shards / "manifest.parquet")
    backup = (shards / "manifest.parquet").read_bytes()
    try:
        pq.write_table(m.replace_schema_metadata({"repacked": "1"}), shards / "manifest.parquet")
        with pytest.raises(RunExistsError, match="manifest changed"):
            train_from_shards(shards, out, cfg, seed=0, log=None, resume=True)
    finally:
        (shards / "manifest.parquet").write_bytes(backup)
    assert (out / "split.json").read_bytes() == split0
    assert train_from_shards(shards, out, cfg, seed=0, log=None, resume=True)["steps"] == 5


def test_captured_only_run_draws_no_free_targets(shards, tmp_path):
    cfg = _cfg()
    cfg.train.steps = 6
    cfg.train.sampler.use_free_views = False
    m = train_from_shards(shards, tmp_path / "a", cfg, seed=0, log=None)
    assert m["free_target_share"] == 0 and m["use_free_views"] is False


# --------------------------------------------------------------------------- CLI and flow
def test_cli_builds_config_and_refuses_bad_input(monkeypatch, shards, tmp_path, capsys):
    import flows.train_lvsm as F
    from flows import cli

    got = {}

    def fake_flow(**kw):
        got.update(kw)
        return {k: 0 for k in ("out", "steps", "resumed_from", "final_train_loss",
                               "final_train_psnr", "heldout_loss", "heldout_psnr",
                               "best_heldout_psnr", "best_heldout_step", "it_s",
                               "wall_seconds")}

    monkeypatch.setattr(F, "train_lvsm_flow", fake_flow)
    rc = cli.main(["train-lvsm", str(shards), "--steps", "7", "--seed", "2", "--no-free-views",
                   "--set", "train.batch_size=3", "--set", 'heldout_scenes=["scene_00"]'])
    assert rc == 0
    cfg = got["config"]
    assert cfg.train.steps == 7 and cfg.train.batch_size == 3 and got["seed"] == 2
    assert cfg.train.sampler.use_free_views is False and cfg.heldout_scenes == ["scene_00"]
    assert got["out"] == str(shards.parent / "shards-lvsm" / "seed2") and not got["resume"]
    assert cli.main(["train-lvsm", str(tmp_path)]) == 2
    assert "no shard manifest" in capsys.readouterr().err
    assert cli.main(["train-lvsm", str(shards), "--set", "train.steps=0"]) == 2


@pytest.fixture(scope="module")
def harness():
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=120):
        yield


def test_flow_via_cli_artifacts_and_resume(harness, shards, tmp_path, capsys):
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterKey

    from flows import cli
    from flows.train_lvsm import ARTIFACT_KEY

    out = tmp_path / "run"
    argv = ["train-lvsm", str(shards), "--out", str(out), "--steps", "10", "--seed", "1",
            *TINY_SET]
    assert cli.main(argv) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["steps"] == 10 and printed["resumed_from"] == 0
    assert (out / "loss.png").is_file() and (out / "ckpt" / "last.pt").is_file()
    with get_client(sync_client=True) as c:
        arts = c.read_artifacts(artifact_filter=ArtifactFilter(
            key=ArtifactFilterKey(any_=[ARTIFACT_KEY, f"{ARTIFACT_KEY}-progress"])))
    kinds = {a.key: a for a in arts}
    assert kinds[f"{ARTIFACT_KEY}-progress"].data == 100.0
    md = kinds[ARTIFACT_KEY].data
    assert "held-out PSNR" in md and "data:image/png;base64," in md

    assert cli.main(argv) == 2  # a run is there: --resume needed
    assert "--resume" in capsys.readouterr().err
    assert cli.main([*argv[:4], "--steps", "15", *argv[6:], "--resume"]) == 2  # another config
    assert "another config" in capsys.readouterr().err
    assert cli.main([*argv, "--resume"]) == 0  # finished: nothing left, same numbers
    again = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert again["resumed_from"] == 10 and again["heldout_loss"] == printed["heldout_loss"]
