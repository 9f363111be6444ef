"""One name per stage: the Prefect task, its run name, the checkpoint key, the progress label
and the entry module agree (ingest, reconstruct, select, freeviews, publish)."""

from __future__ import annotations

import importlib
import inspect
from pathlib import Path
from types import SimpleNamespace

from schemas.pipeline import PipelineConfig
from tasks import scene_tasks as T
from tasks.scene_tasks import STAGE_ROOTS

STAGES = ("ingest", "reconstruct", "select", "freeviews", "publish")
REPO = Path(__file__).resolve().parents[2]


def test_task_names_are_the_stage_keys():
    assert tuple(STAGE_ROOTS) == STAGES
    for name in STAGES:
        task = getattr(T, name)  # the Python name is the stage name too
        assert task.name == name
        assert task.task_run_name.startswith(f"{name}[")


def test_each_stage_checkpoints_under_its_own_name():
    """``run_stage(..., "<stage>", ...)`` in each stage task uses its task's name (publish
    writes no checkpoint; its status stage is "publish")."""
    for name in STAGES:
        src = inspect.getsource(getattr(T, name).fn)
        assert f'"{name}"' in src, name
    from freescale_core.eval.sweep import STAGES as SWEEP_STAGES

    assert tuple(SWEEP_STAGES) == STAGES


def test_entry_modules_import_and_no_second_stage_module():
    for roots in STAGE_ROOTS.values():
        for m in roots:
            importlib.import_module(m)
    # tasks/stage.py is the checkpoint mechanism; no stage package has a stage.py beside it
    assert not list((REPO / "freescale_core").rglob("stage.py"))


def test_freeviews_progress_is_labelled_with_the_stage_name(monkeypatch, tmp_path):
    """The progress record (and the Prefect progress artifact) of the freeviews stage says
    "freeviews", the stage the status names while it runs (was "render-filter-rectify")."""
    import freescale_core.freeviews.run as fv_mod
    import freescale_core.scene.ply as ply_mod

    seen = {}

    def fake_stage(*args, **kw):
        seen.update(kw)
        return SimpleNamespace(counts={"n_free_views": 0})

    monkeypatch.setattr(fv_mod, "run_free_view_stage", fake_stage)
    monkeypatch.setattr(ply_mod, "read_ply", lambda *a, **k: None)
    monkeypatch.setattr(ply_mod, "read_background",  # no PLY here: the configured colour
                        lambda path, default=(0.0, 0.0, 0.0), scene_id=None: tuple(default))
    monkeypatch.setattr(T, "load_stage_output",
                        lambda *a, **k: SimpleNamespace(views_for=lambda split: (None, None)))
    calls = []

    def fake_run_stage(root, sid, stage, cfg, up, mods, seed, compute):
        calls.append(stage)
        return compute(tmp_path)

    monkeypatch.setattr(T, "run_stage", fake_run_stage)
    ref = SimpleNamespace(scene_id="s", result={"train_scale": 1.0})
    T.freeviews.fn(str(tmp_path), ref, ref, ref, str(tmp_path), PipelineConfig.from_preset("fast"))
    assert calls == ["freeviews"]
    assert seen["progress"].stage == "freeviews"


def test_a_stale_progress_record_of_another_stage_name_is_not_shown(tmp_path):
    """A store left by a run of the old names (progress.json labelled
    "render-filter-rectify") shows the running stage by its name, without the stale bar."""
    from flows.progress_view import _snapshot
    from freescale_core.store.store import Store
    from freescale_core.store.progress import PROGRESS_NAME, ProgressFile

    st = Store(tmp_path)
    st.update_status("a", status="running", stage="freeviews")
    pf = ProgressFile(st.work_dir("a", create=True) / PROGRESS_NAME, "render-filter-rectify",
                      10, "views", every=0.0)
    pf.update(3)
    done, running = _snapshot(st, ["a"])
    assert done == [] and running == {"a": {"stage": "freeviews"}}
