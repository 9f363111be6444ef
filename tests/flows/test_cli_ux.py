"""What a user sees from the command line: help built from the configs, config show, the
manifest's headline columns, resume of a store made by any caller, deployment steps."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from flows.cli import build_parser, main
from flows.cli.config import config_markdown, field_docs, help_epilog, iter_fields
from schemas.pipeline import PipelineConfig, resolve_preset

REPO = Path(__file__).resolve().parents[2]


def test_every_config_field_is_in_run_help_with_its_default(capsys):
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    out = capsys.readouterr().out
    names = [n for n, _, _ in iter_fields(PipelineConfig)]
    assert len(names) > 100
    for n in names:
        assert f"\n  {n} (" in out, n
    assert out.count("default:") >= len(names)
    flat = " ".join(out.split())
    assert "--preset {auto,paper,cpu,fast}" in flat and "(default: auto)" in flat


def test_field_docs_are_one_short_line():
    for f in field_docs():
        assert f.doc, f"{f.name} has no description"
        assert len(f.doc) <= 110, f"{f.name}: {len(f.doc)} chars; move the rationale to docs/"
        assert "\n" not in f.doc


def test_docs_config_md_is_current():
    assert (REPO / "docs" / "CONFIG.md").read_text() == config_markdown(), (
        "regenerate: python -m flows.cli.config --markdown > docs/CONFIG.md")


def test_defaults_per_preset_come_from_the_preset_table():
    d = {f.name: f.defaults for f in field_docs()}
    assert d["recon.max_iterations"] == {
        p: PipelineConfig.from_preset(p).recon.max_iterations for p in ("paper", "cpu", "fast")}
    assert "paper: 30000" in help_epilog("cpu")


def test_auto_preset_resolves_once_and_is_recorded(monkeypatch):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_preset("auto") == "cpu"
    c = PipelineConfig.from_preset("auto", {"seed": 2})
    assert c.preset == "cpu" and c == PipelineConfig.from_preset("cpu", {"seed": 2})
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert PipelineConfig.model_validate({"preset": "auto"}).preset == "paper"
    assert resolve_preset("fast") == "fast"


def test_config_show_and_version(capsys):
    assert main(["config", "show", "--preset", "fast", "--set", "select.nms.max_views=7",
                 "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["preset"] == "fast" and d["select"]["nms"]["max_views"] == 7
    assert PipelineConfig.model_validate(d) == PipelineConfig.from_preset(
        "fast", {"select": {"nms": {"max_views": 7}}})
    assert main(["config", "show", "--preset", "cpu"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("# preset cpu") and yaml.safe_load(out)["recon"]["max_seconds"] == 600
    assert main(["config", "show", "--set", "select.nms.nope=1"]) == 2
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.startswith("freescale ")
    assert main(["config", "fields", "--json"]) == 0
    rows = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert {r["name"] for r in rows} >= {"seed", "select.nms.max_views", "recon.max_seconds"}


def test_resume_accepts_set_and_a_flow_written_run_config(tmp_path, monkeypatch, capsys):
    """A store made by a deployment has run_config.json with the full config; resume uses
    it, and --set fixes a field."""
    import flows.cli.run as cli

    seen = {}

    def fake_run_flow(scenes, store, preset, overrides, scale_out, workers, dask, force,
                      progress=True, config=None):
        seen.update(scenes=scenes, preset=preset, overrides=overrides, config=config,
                    scale_out=scale_out)
        return 0

    monkeypatch.setattr(cli, "run_flow", fake_run_flow)
    cfg = PipelineConfig.from_preset("fast")
    (tmp_path / "run_config.json").write_text(json.dumps(
        {"scenes": ["a"], "preset": "fast", "config": cfg.model_dump(mode="json"),
         "scale_out": "threads", "workers": 1, "dask_address": None}))
    assert main(["resume", str(tmp_path), "--set", "select.nms.max_views=9"]) == 0
    assert seen["config"]["preset"] == "fast"
    assert seen["overrides"] == {"select": {"nms": {"max_views": 9}}}
    assert main(["resume", str(tmp_path / "nope")]) == 2


def test_flow_writes_run_config(tmp_path):
    from flows.generate_dataset import _write_run_config

    cfg = PipelineConfig.from_preset("fast", {"seed": 4})
    (tmp_path / "x" / "a").mkdir(parents=True)
    _write_run_config(str(tmp_path), [str(tmp_path / "x" / "*")], cfg, "threads", 2, None)
    rc = json.loads((tmp_path / "run_config.json").read_text())
    assert rc["scenes"] == [str((tmp_path / "x" / "a").resolve())]  # absolute, globs expanded
    assert PipelineConfig.model_validate(rc["config"]) == cfg


def test_manifest_table_shows_free_views_scarce_and_psnr(tmp_path, capsys):
    from freescale_core.store.store import Store

    st = Store(tmp_path)
    st.update_status("a", status="ok", counts={"n_selected": 17, "n_free_views": 16},
                     info={"scarce": True, "recon_train_psnr": 31.5})
    assert main(["scenes", "ls", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    for col in ("n_free_views", "scarce", "recon_train_psnr", "recon_test_psnr"):
        assert col in out
    assert "n_final" not in out and "31.5" in out


def test_long_listing_prints_plain_rows_with_the_same_cells(tmp_path, capsys, monkeypatch):
    """Beyond TABLE_MAX_ROWS scenes ``scenes ls`` prints aligned plain rows (a drawn table of
    10,000 rows took ~15 s): one header, one line per scene, the same columns."""
    from flows.cli import scenes
    from freescale_core.store.store import Store

    st = Store(tmp_path)
    for i in range(3):
        st.update_status(f"s{i}", status="ok", counts={"n_free_views": 10 + i},
                         info={"recon_train_psnr": 30.25 + i})
    monkeypatch.setattr(scenes, "TABLE_MAX_ROWS", 2)
    assert main(["scenes", "ls", str(tmp_path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "(3 scenes)" in lines[0] and lines[1].split()[:3] == ["scene_id", "status", "n_free_views"]
    assert [ln.split()[:3] for ln in lines[2:]] == [["s0", "ok", "10"], ["s1", "ok", "11"],
                                                     ["s2", "ok", "12"]]
    assert "31.2" in lines[3] and "┃" not in "".join(lines)


def test_read_only_commands_do_not_import_prefects_server(tmp_path):
    """``scenes ls`` and friends start no flow: the reaper (and with it Prefect's server, seconds
    to import) is not loaded."""
    import subprocess
    import sys

    from freescale_core.store.store import Store

    Store(tmp_path).update_status("a", status="ok")
    code = ("import sys; from flows.cli import main; rc = main(['scenes', 'ls', sys.argv[1], "
            "'--json']); print('SERVER' if 'prefect.server.api.server' in sys.modules else 'NONE'); "
            "sys.exit(rc)")
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "NONE"


def test_shards_show_config_needs_a_published_config(tmp_path, capsys):
    from freescale_core.store.store import Store, write_json_atomic

    st = Store(tmp_path)
    st.update_status("a", status="ok")
    assert main(["scenes", "show", str(tmp_path), "a", "--config"]) == 2
    cfg = PipelineConfig.from_preset("fast")
    with st.publish("a") as out:
        write_json_atomic(out / "config.json", cfg.model_dump(mode="json"))
    capsys.readouterr()
    assert main(["scenes", "show", str(tmp_path), "a", "--config"]) == 0
    assert PipelineConfig.model_validate(json.loads(capsys.readouterr().out)) == cfg


def test_subcommands_show_defaults():
    p = build_parser()
    sub = p._subparsers._group_actions[0].choices
    assert "(default: 36)" in sub["sample-scene"].format_help()


# ---------------------------------------------------------------------- deployments
def test_pull_step_enters_the_project_from_anywhere(tmp_path, monkeypatch):
    """prefect.yaml's pull step, resolved and called the way Prefect's step runner does
    (import the step by name, call it with its inputs) in a worker's temporary folder."""
    from prefect.utilities.importtools import import_object

    doc = yaml.safe_load((REPO / "prefect.yaml").read_text())
    assert "/app" not in json.dumps(doc["pull"]) and len(doc["pull"]) == 1
    (fqn, inputs), = doc["pull"][0].items()
    step = import_object(fqn)
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("FREESCALE_HOME", raising=False)
    out = step(**(inputs or {}))
    assert Path.cwd() == REPO and out["directory"] == str(REPO)
    monkeypatch.setenv("FREESCALE_HOME", str(tmp_path))
    with pytest.raises(FileNotFoundError, match="not a FreeScale project"):
        step(**(inputs or {}))


def test_compose_has_no_top_level_name_and_no_telemetry():
    doc = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    assert "name" not in doc  # rejected by the docker-compose v1 tool
    for s in ("prefect-server", "worker"):
        assert doc["services"][s]["environment"]["DO_NOT_TRACK"] == "1"
    ignore = (REPO / ".dockerignore").read_text().split()
    assert {".venv/", "data/", ".git/"} <= set(ignore)
    assert "DO_NOT_TRACK" in (REPO / "Makefile").read_text()
    assert "DO_NOT_TRACK=1" in (REPO / ".ci" / "run").read_text()


def test_local_dask_workers_report_to_the_flows_server(monkeypatch):
    """A local Dask cluster's workers get the address of this process's temporary Prefect
    server (each started a server of its own before); a user's PREFECT_API_URL is inherited."""
    from prefect.server.api.server import SubprocessASGIServer

    from flows.generate_dataset import _prefect_env_for_workers, make_task_runner

    class Fake:
        running, api_url = True, "http://127.0.0.1:8765/api"

    monkeypatch.delenv("PREFECT_API_URL", raising=False)
    monkeypatch.setattr(SubprocessASGIServer, "_instances", {None: Fake()})
    assert _prefect_env_for_workers() == {"PREFECT_API_URL": Fake.api_url}
    runner = make_task_runner("dask", None, 2)
    assert runner.cluster_kwargs["env"] == {"PREFECT_API_URL": Fake.api_url}
    monkeypatch.setenv("PREFECT_API_URL", "http://127.0.0.1:4200/api")
    assert _prefect_env_for_workers() == {}
