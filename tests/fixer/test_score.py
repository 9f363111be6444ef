"""`freescale fixer score`: held-out raw / reproject / fixed on a store, JSON keys, errors."""

from __future__ import annotations

import copy
import json

import pytest

from flows.cli import main
from tests.conftest import TINY_OVERRIDES, build_store


@pytest.fixture(scope="module")
def ood_store(tmp_path_factory):
    from freescale_core.scene.sample import write_sample_scene

    root = tmp_path_factory.mktemp("score")
    write_sample_scene(root / "s", n_views=16, width=96, height=72, seed=1)
    over = copy.deepcopy(TINY_OVERRIDES)
    over["recon_split"] = "every8"
    return build_store(root / "store", {"s": root / "s"}, over)


def test_score_json_has_the_documented_keys(ood_store, capsys):
    assert main(["fixer", "score", str(ood_store), "--json"]) == 0
    rows = [json.loads(x) for x in capsys.readouterr().out.splitlines() if x.startswith("{")]
    assert [r["scene_id"] for r in rows] == ["s"]
    r = rows[0]
    for k in ("heldout_psnr_raw", "heldout_psnr_fixed", "heldout_ssim_raw",
              "heldout_ssim_fixed", "heldout_psnr_reproject"):
        assert isinstance(r[k], float) and r[k] == r[k], k  # a number, not NaN
    assert r["recon_split"] == "every8" and r["heldout_views"] == 2
    # the sample scene carries its exact renderer: the free views are scored against it
    assert "oracle_psnr_raw" in r and "oracle_psnr_fixed" in r


def test_score_errors_are_one_line(ood_store, tmp_path, capsys):
    assert main(["fixer", "score", str(tmp_path)]) == 2
    assert "is not a store" in capsys.readouterr().err
    assert main(["fixer", "score", str(ood_store), "--scenes", "nope"]) == 1
    assert "scene 'nope' is not in" in capsys.readouterr().err
    assert main(["fixer", "score", str(ood_store), "--checkpoint", str(tmp_path / "x.pt")]) == 2
    assert "x.pt" in capsys.readouterr().err
