"""The yield funnel of benchmarks.freeviews read from a published store (issue 63)."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest

from benchmarks.freeviews import published_funnel


@pytest.fixture(scope="module")
def store(dataset_store):
    return dataset_store  # the session's published store (tests/conftest.py)


def test_published_funnel_equals_the_stage_counts(store):
    """Feasible, NMS-selected, reserve drawn, passed, kept and the mean predicted PSNR of the
    kept views read back from views.parquet equal what the stages recorded."""
    f = published_funnel(store, "sample_a")
    work = store / "scenes" / "sample_a" / "_work"
    sel = json.loads((work / "select.done.json").read_text())["result"]
    fv = json.loads((work / "freeviews.done.json").read_text())["result"]
    assert f["n_feasible"] == sel["n_feasible"] > 0
    assert f["n_selected"] == sel["n_selected"]
    assert f["reserve_drawn"] == fv["reserve_drawn"]
    assert f["n_selected"] + f["reserve_drawn"] == fv["candidates"]
    assert (f["passed"], f["kept"]) == (fv["passed"], fv["final"])
    with open(work / "freeviews.pkl", "rb") as fh:
        res = pickle.load(fh)
    kept = [r.pred_psnr for r in res.records if r.final]
    assert f["mean_pred_psnr"] == pytest.approx(float(np.mean(kept)), abs=1e-9)
    assert np.isfinite(f["mean_true_psnr"])  # the sample scene has an oracle ...
    assert res.timings["ground_truth"] > 0  # ... whose renders are a part of their own


def test_published_funnel_names_a_scene_that_was_not_published(store):
    with pytest.raises(SystemExit, match="nope"):
        published_funnel(store, "nope")
