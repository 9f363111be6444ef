"""Stage keys derived from the code: an edit invalidates exactly the stages that import the
edited module (transitively) and the stages after them."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from freescale_core.codekey import LAYERS, REPO, clear_cache, code_key, reached
from tasks.scene_tasks import STAGE_ROOTS
from tasks.stage import StageRef, stage_key

CHAIN = (("ingest", ()), ("reconstruct", ("ingest",)), ("select", ("ingest", "reconstruct")),
         ("freeviews", ("ingest", "reconstruct", "select")))


def _keys(root: Path) -> dict[str, str]:
    """Each stage's checkpoint key as run_stage computes it, upstream keys chained (read
    afresh: the tree may have been edited since the last call)."""
    clear_cache()
    refs: dict[str, StageRef] = {}
    for stage, ups in CHAIN:
        k = stage_key(stage, {"c": 1}, [refs[u] for u in ups], STAGE_ROOTS[stage], 0, root=root)
        refs[stage] = StageRef("s", stage, k, {})
    return {s: r.key for s, r in refs.items()}


@pytest.fixture
def tree(tmp_path) -> Path:
    for top in LAYERS:
        shutil.copytree(REPO / top, tmp_path / top,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    return tmp_path


def _append_comment(root: Path, rel: str) -> None:
    with open(root / rel, "a") as f:
        f.write("\n# an edit\n")


def test_the_copy_keys_like_the_installed_tree(tree):
    assert _keys(tree) == _keys(REPO)


@pytest.mark.parametrize("rel, changed", [
    ("freescale_core/recon/bounds.py", {"reconstruct", "select", "freeviews"}),
    ("freescale_core/recon/photometric.py", {"reconstruct", "select", "freeviews"}),
    ("freescale_core/scene/triangulate.py", {"reconstruct", "select", "freeviews"}),
    ("freescale_core/freeviews/trust.py", {"freeviews"}),
    ("freescale_core/scene/io/colmap.py", {"ingest", "reconstruct", "select", "freeviews"}),
    ("freescale_core/select/nms.py", {"select", "freeviews"}),
    ("freescale_core/downstream/refine.py", set()),
])
def test_an_edit_invalidates_exactly_the_stages_that_reach_it(tree, rel, changed):
    before = _keys(tree)
    _append_comment(tree, rel)
    after = _keys(tree)
    assert {s for s in before if before[s] != after[s]} == changed


def test_dependency_versions_enter_the_key(tree, monkeypatch):
    import freescale_core.codekey as ck

    k = code_key(("freescale_core.recon.trainer",), tree)
    monkeypatch.setattr(ck, "_KEYS", {})
    monkeypatch.setattr(ck, "dependency_versions", lambda: {"torch": "9.9", "numba": "0",
                                                            "pycolmap": "0"})
    assert code_key(("freescale_core.recon.trainer",), tree) != k


def test_the_walk_follows_function_local_imports():
    # trainer imports the photometric fit inside a function; bounds through the strategy
    got = reached(STAGE_ROOTS["reconstruct"])
    assert {"freescale_core.recon.bounds", "freescale_core.recon.photometric",
            "freescale_core.scene.triangulate"} <= got
    assert "freescale_core.freeviews.trust" in reached(STAGE_ROOTS["freeviews"])


def test_an_unknown_root_is_an_error():
    with pytest.raises(ValueError, match="no project module"):
        code_key(("freescale_core.nonexistent",))


def test_every_cached_thing_uses_the_code_key(monkeypatch, tmp_path):
    """Sweep points, held-out scores and refinement arms: one scheme, so a code edit
    invalidates each of them (code_key stubbed to stand for an edit)."""
    import freescale_core.codekey as ck
    from freescale_core.downstream.refine import refine_key
    from freescale_core.eval.downstream import refine_part_name
    from freescale_core.eval.heldout import heldout_eval_name
    from freescale_core.eval.sweep import point_key
    from schemas.pipeline import PipelineConfig
    from schemas.refine import RefineConfig

    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "a.txt").write_text("x")

    def keys():
        return (refine_key(RefineConfig()), refine_part_name(RefineConfig()),
                heldout_eval_name(256), point_key(tmp_path / "scene", PipelineConfig()))

    monkeypatch.setattr(ck, "code_key", lambda roots, root=REPO: "0" * 16)
    a = keys()
    monkeypatch.setattr(ck, "code_key", lambda roots, root=REPO: "1" * 16)
    b = keys()
    assert all(x != y for x, y in zip(a, b)), (a, b)
