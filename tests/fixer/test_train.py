"""Fixer training (freescale_core.fixer.train, flows/train_fixer.py): the loss falls on pairs a
warp can correct, same seed same weights, resume (in process and after SIGKILL) gives the
uninterrupted weights, mismatched resumes and bad input are refused, the CLI and the flow."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from freescale_core.fixer.model import load_fixer
from freescale_core.fixer.train import (ResumeMismatchError, RunExistsError, data_hash,
                                        fixer_loss, train_fixer)
from freescale_core.fixer.data import pair_folders
from schemas.fixer import FixerTrainConfig
from tests.fixer.fixer_synth import make_pairs

REPO = Path(__file__).resolve().parents[2]
# a small model and tiny patches: a step is a few ms
TINY = dict(steps=20, batch_size=2, patch=24, warmup_steps=2, ckpt_every=5, log_every=5,
            eval_pairs=2, model=dict(base_channels=8))


def _cfg(**over) -> FixerTrainConfig:
    d = {**TINY, **over}
    d["model"] = {**TINY["model"], **over.get("model", {})}
    return FixerTrainConfig.model_validate(d)


@pytest.fixture(scope="module")
def pairs(tmp_path_factory) -> Path:
    return make_pairs(tmp_path_factory.mktemp("fixer") / "pairs", n=2, H=32, W=40)


@pytest.fixture(scope="module")
def full_run(pairs, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("full") / "run"
    return out, train_fixer(pairs, out, _cfg(), holdout_scenes=["sc"], log=None)


def _weights(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)["model"]


def _assert_same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_files_checkpoint_meta_and_curve(pairs, full_run):
    out, m = full_run
    for f in ("fixer.pt", "ckpt/last.pt", "loss.jsonl", "metrics.json", "loss.png",
              "contact.png"):
        assert (out / f).is_file(), f
    model, meta = load_fixer(out / "fixer.pt", k=2)
    assert meta["train_scenes"] == ["sa", "sb"] and meta["holdout_scenes"] == ["sc"]
    assert meta["config"]["steps"] == 20 and meta["config"]["model"]["base_channels"] == 8
    assert meta["data_hash"] == data_hash([f for f in pair_folders(pairs)
                                           if f.parent.name != "sc"])
    assert meta["pairs_root"] == str(pairs.resolve()) and meta["steps"] == 20
    rows = [json.loads(x) for x in (out / "loss.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [5, 10, 15, 20]
    assert all(np.isfinite(r["loss"]) and r["patches_s"] > 0 for r in rows)
    assert m["eval_on"] == "holdout" and {r["scene_id"] for r in m["eval_pairs"]} == {"sc"}
    assert (out / "contact.png").read_bytes()[:4] == b"\x89PNG"


def test_loss_falls_and_fixes_held_out_pairs(pairs, tmp_path):
    """Targets are a blurred, shifted render's truth and warp 0 carries them: a fixer must
    learn to use the warp, also on the held-out scene."""
    m = train_fixer(pairs, tmp_path / "run", _cfg(steps=40, batch_size=4, patch=32,
                                                  log_every=10, ckpt_every=40, lr=3e-3),
                    holdout_scenes=["sc"], log=None)
    rows = [json.loads(x) for x in (tmp_path / "run" / "loss.jsonl").read_text().splitlines()]
    # measured: loss 0.244 -> 0.195, held-out PSNR 14.82 -> 16.15 dB, SSIM 0.43 -> 0.61
    assert rows[-1]["loss"] < 0.9 * rows[0]["loss"], [r["loss"] for r in rows]
    assert m["eval_psnr_fixed"] > m["eval_psnr_render"] + 0.8, m
    assert m["eval_ssim_fixed"] > m["eval_ssim_render"]


def test_same_seed_same_weights_other_seed_differs(pairs, tmp_path):
    cfg = _cfg(steps=4, ckpt_every=4)
    train_fixer(pairs, tmp_path / "a", cfg, holdout_scenes=["sc"], log=None)
    train_fixer(pairs, tmp_path / "b", cfg, holdout_scenes=["sc"], log=None)
    train_fixer(pairs, tmp_path / "c", _cfg(steps=4, ckpt_every=4, seed=1),
                holdout_scenes=["sc"], log=None)
    a, b, c = (_weights(tmp_path / x / "fixer.pt") for x in "abc")
    _assert_same(a, b)
    assert not all(torch.equal(a[k], c[k]) for k in a)


def test_resume_in_process_equals_uninterrupted(pairs, full_run, tmp_path):
    out = tmp_path / "cut"

    class Stop(Exception):
        pass

    def stop_at_12(step, total, rec):
        if step == 12:
            raise Stop

    with pytest.raises(Stop):
        train_fixer(pairs, out, _cfg(), holdout_scenes=["sc"], log=None, progress=stop_at_12)
    assert torch.load(out / "ckpt" / "last.pt", weights_only=False)["step"] == 10
    assert not (out / "fixer.pt").exists()
    with pytest.raises(RunExistsError, match="already holds a fixer run"):
        train_fixer(pairs, out, _cfg(), holdout_scenes=["sc"], log=None)
    m = train_fixer(pairs, out, _cfg(), holdout_scenes=["sc"], log=None, resume=True)
    assert m["resumed_from"] == 10
    _assert_same(_weights(full_run[0] / "fixer.pt"), _weights(out / "fixer.pt"))
    rows = [json.loads(x) for x in (out / "loss.jsonl").read_text().splitlines()]
    ref = [json.loads(x) for x in (full_run[0] / "loss.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [5, 10, 15, 20]  # the lines past step 10 were redone
    assert [r["loss"] for r in rows] == [r["loss"] for r in ref]


def test_sigkill_then_resume_equals_uninterrupted(pairs, full_run, tmp_path):
    out = tmp_path / "killed"
    code = (
        "import os, signal, torch\n"
        f"torch.set_num_threads({torch.get_num_threads()})\n"
        "from freescale_core.fixer.train import train_fixer\n"
        "from schemas.fixer import FixerTrainConfig\n"
        "def cb(step, total, rec):\n"
        "    if step == 13:\n"
        "        os.kill(os.getpid(), signal.SIGKILL)\n"
        f"train_fixer({str(pairs)!r}, {str(out)!r}, "
        f"FixerTrainConfig.model_validate({_cfg().model_dump(mode='json')!r}), "
        "holdout_scenes=['sc'], log=None, progress=cb)\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=300, check=False)
    assert r.returncode == -signal.SIGKILL, r.stderr[-2000:]
    assert not (out / "fixer.pt").exists()
    m = train_fixer(pairs, out, _cfg(), holdout_scenes=["sc"], log=None, resume=True)
    assert m["resumed_from"] == 10
    _assert_same(_weights(full_run[0] / "fixer.pt"), _weights(out / "fixer.pt"))


def test_resume_refuses_other_config_data_or_pairs(pairs, full_run, tmp_path):
    out = full_run[0]
    with pytest.raises(ResumeMismatchError, match="another config .*lr"):
        train_fixer(pairs, out, _cfg(lr=1e-4), holdout_scenes=["sc"], log=None, resume=True)
    with pytest.raises(ResumeMismatchError, match="held out"):
        train_fixer(pairs, out, _cfg(), holdout_scenes=["sb"], log=None, resume=True)
    other = make_pairs(tmp_path / "pairs2", n=2, H=32, W=40)  # same content, another root
    with pytest.raises(ResumeMismatchError, match="trained on pairs .* not "):
        train_fixer(other, out, _cfg(), holdout_scenes=["sc"], log=None, resume=True)
    # the same root with a remade scene: the data hash changes
    import shutil
    moved = tmp_path / "pairs3"
    shutil.copytree(pairs, moved)
    ck = tmp_path / "ck"
    shutil.copytree(out, ck)
    st = torch.load(ck / "ckpt" / "last.pt", weights_only=False)
    st["pairs_root"] = str(moved.resolve())
    torch.save(st, ck / "ckpt" / "last.pt")
    make_pairs(moved, scenes=("sa",), n=2, H=32, W=40, seed=5)
    with pytest.raises(ResumeMismatchError, match="changed since the run started"):
        train_fixer(moved, ck, _cfg(), holdout_scenes=["sc"], log=None, resume=True)


def test_bad_input_is_refused(pairs, tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        train_fixer(tmp_path / "nope", tmp_path / "o", _cfg(), log=None)
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no complete pair folder"):
        train_fixer(tmp_path / "empty", tmp_path / "o", _cfg(), log=None)
    with pytest.raises(ValueError, match="scene 'zz' has no pairs"):
        train_fixer(pairs, tmp_path / "o", _cfg(), holdout_scenes=["zz"], log=None)
    with pytest.raises(ValueError, match="no training scene left"):
        train_fixer(pairs, tmp_path / "o", _cfg(), holdout_scenes=["sa", "sb", "sc"], log=None)


def test_cpu_budget_stops_early(pairs, tmp_path):
    m = train_fixer(pairs, tmp_path / "b", _cfg(steps=10_000, max_cpu_seconds=0.5),
                    holdout_scenes=["sc"], log=None)
    assert m["stopped_by"] == "cpu_seconds" and 0 < m["steps"] < 10_000


def test_loss_ignores_masked_pixels_and_confidence_follows_error():
    torch.manual_seed(0)
    f = torch.rand(2, 3, 16, 16, requires_grad=True)
    t = torch.rand(2, 3, 16, 16)
    c = torch.full((2, 1, 16, 16), 0.5)
    m = torch.ones(2, 16, 16, dtype=torch.bool)
    m[:, :, 8:] = False
    loss, _ = fixer_loss(f, c, t, m)
    loss.backward()
    assert float(f.grad[..., 8:].abs().sum()) == 0 and float(f.grad[..., :8].abs().sum()) > 0
    t2 = t.clone()
    t2[..., 8:] = 1 - t2[..., 8:]  # what the target shows outside the mask does not count
    assert float(fixer_loss(f.detach(), c, t2, m)[0]) == pytest.approx(float(loss.detach()), abs=1e-6)
    # a confidence high where the error is low scores better than the reverse
    fe = t.clone()
    fe[:, :, :4] += 0.3
    fe = fe.clamp(0, 1)
    good = torch.where(torch.arange(16)[:, None] < 4, 0.1, 0.9).expand(2, 1, 16, 16)
    bad = 1 - good
    m1 = torch.ones(2, 16, 16, dtype=torch.bool)
    assert fixer_loss(fe, good, t, m1)[1]["conf"] < fixer_loss(fe, bad, t, m1)[1]["conf"]


# --------------------------------------------------------------------------- CLI and flow
def test_cli_refuses_bad_input(pairs, tmp_path, capsys):
    from flows import cli

    assert cli.main(["train-fixer", str(tmp_path / "nope"), str(tmp_path / "o")]) == 2
    assert "no fixer pairs under" in capsys.readouterr().err
    assert cli.main(["train-fixer", str(pairs), str(tmp_path / "o"), "--steps", "0"]) == 2
    assert "steps" in capsys.readouterr().err


@pytest.fixture(scope="module")
def harness():
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=120):
        yield


def test_flow_via_cli_artifacts_and_resume(harness, pairs, tmp_path, capsys):
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterKey

    from flows import cli
    from flows.train_fixer import ARTIFACT_KEY

    out = tmp_path / "run"
    sets = [x for kv in ("batch_size=2", "patch=24", "log_every=5", "ckpt_every=5",
                         "warmup_steps=2", "model.base_channels=8")
            for x in ("--set", kv)]
    argv = ["train-fixer", str(pairs), str(out), "--holdout", "sc", "--steps", "10",
            "--seed", "1", *sets]
    assert cli.main(argv) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["steps"] == 10 and printed["holdout_scenes"] == ["sc"]
    assert (out / "fixer.pt").is_file()
    with get_client(sync_client=True) as c:
        arts = c.read_artifacts(artifact_filter=ArtifactFilter(
            key=ArtifactFilterKey(any_=[ARTIFACT_KEY, f"{ARTIFACT_KEY}-progress"])))
    kinds = {a.key: a for a in arts}
    assert kinds[f"{ARTIFACT_KEY}-progress"].data == 100.0
    md = kinds[ARTIFACT_KEY].data
    assert md.count("data:image/png;base64,") == 2 and "Before / after" in md

    assert cli.main(argv) == 2  # a run is there: --resume needed
    assert "--resume" in capsys.readouterr().err
    assert cli.main([*argv[:7], "--steps", "12", *argv[9:], "--resume"]) == 2
    assert "another config" in capsys.readouterr().err
    assert cli.main([*argv, "--resume"]) == 0  # finished: nothing left, same weights
    again = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert again["resumed_from"] == 10 and again["eval_psnr_fixed"] == printed["eval_psnr_fixed"]


def test_augmentations_move_inputs_and_target_together():
    """Flip and gain hit render, warps and target alike: where they agree before, they agree
    in every patch; alpha and weights are never changed."""
    from freescale_core.fixer.train import _Pool
    from tests.fixer.fixer_synth import make_sample

    s = make_sample(np.random.default_rng(0), "sa", 0, 32, 40)
    s.target = s.render.copy()
    s.warps[0] = s.render
    s.warp_weight[0] = np.linspace(0, 1, 40)[None].repeat(32, 0)
    pool = _Pool([s], k=2)
    x, y, _ = pool.batch(np.random.default_rng(1), 16, 24, flip=True, jitter=0.2)
    assert torch.equal(x[:, :3], y) and torch.equal(x[:, 4:7], y)
    assert torch.all(x[:, 3] == 1.0)  # alpha untouched
    w = x[:, 7]
    slope = w[:, :, 1:] - w[:, :, :-1]  # the weight ramp flips with the patch, never rescales
    assert (slope > 0).all(dim=(1, 2)).logical_or((slope < 0).all(dim=(1, 2))).all()
    assert (slope < 0).all(dim=(1, 2)).any() and (slope > 0).all(dim=(1, 2)).any()


def test_fine_tune_starts_from_the_given_fixer(pairs, full_run, tmp_path):
    init = full_run[0] / "fixer.pt"
    m = train_fixer(pairs, tmp_path / "tta", _cfg(steps=3, lr=1e-12, init_from=str(init)),
                    train_scenes=["sc"], log=None)
    assert m["train_scenes"] == ["sc"] and m["init_from"]["train_scenes"] == ["sa", "sb"]
    a, b = _weights(init), _weights(tmp_path / "tta" / "fixer.pt")
    assert all(torch.allclose(a[k], b[k], atol=1e-8) for k in a)  # lr ~0: still the init
    with pytest.raises(ValueError, match="has model config"):
        train_fixer(pairs, tmp_path / "x", _cfg(init_from=str(init), model=dict(base_channels=12)),
                    train_scenes=["sc"], log=None)
