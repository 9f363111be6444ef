"""docker-compose.yml and prefect.yaml are validated here (no Docker engine on this machine)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]


def test_compose_file_is_valid_compose_spec():
    compose_spec = pytest.importorskip("compose_spec", reason="compose-spec not installed")
    text = (REPO / "docker-compose.yml").read_text()
    c = compose_spec.PyCompose.from_yaml(text)  # raises ValueError on an invalid file
    assert set(c.service_names()) == {"postgres", "prefect-server", "worker"}


def test_compose_semantics():
    doc = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    svc = doc["services"]
    # the UI is reachable on localhost only
    assert svc["prefect-server"]["ports"] == ["127.0.0.1:4200:4200"]
    assert "postgresql" in svc["prefect-server"]["environment"]["PREFECT_API_DATABASE_CONNECTION_URL"]
    # workers run the project's own image, built from the Dockerfile, with the store on a volume
    assert svc["worker"]["image"] == svc["prefect-server"]["image"] == "freescale:latest"
    assert (REPO / "Dockerfile").is_file()
    assert any(v.startswith("store:") for v in svc["worker"]["volumes"])
    assert set(doc["volumes"]) >= {"store", "pgdata"}
    # every named volume used is declared
    for s in svc.values():
        for v in s.get("volumes", []):
            src = v.split(":")[0]
            if not src.startswith((".", "/")):
                assert src in doc["volumes"], src


def test_prefect_yaml_entrypoints_exist():
    doc = yaml.safe_load((REPO / "prefect.yaml").read_text())
    for d in doc["deployments"]:
        path, fn = d["entrypoint"].split(":")
        src = (REPO / path).read_text()
        assert f"def {fn}(" in src
        assert d["work_pool"]["name"] == "freescale-process"
