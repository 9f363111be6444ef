"""``--compare`` with the frozen legacy arms: today's ``benchmarks/recon.py`` plus the old trainers.

    .venv/bin/python -m lab.recon_compare kermit --compare old new --cpu-minutes 10 \
        --eval-every 100 --out rows.jsonl

Every option is ``python -m benchmarks.recon``'s; the arms are its arms (``new``, ``new-fast``,
a preset, ``ARM,FIELD=VALUE,...``) and the legacy ones, frozen ``ReconConfig`` dumps in
``lab/arms/<name>.json`` (``old``: the cpu preset before issue 17, ``old-fast``, ``pre55``: the
cpu preset before stop 55), so the product's schema holds no preset of an old trainer. An arm is
a ``ReconConfig`` and the old trainer's switches (``lab/legacy.py``: plug-ins of today's loop,
handed to the benchmark's trainer as ``run(..., plugins=)``); ``--set`` and ``ARM,FIELD=VALUE``
take the switches too (e.g. ``new,ssim_impl=torch``). Rows record the switches under their old
keys in ``config``, as rows did before they left the schema.
"""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks import recon
from lab import legacy
from schemas.recon import ReconConfig

ARMS_DIR = Path(__file__).resolve().parent / "arms"
LEGACY_ARMS = ("old", "old-fast", "pre55")


def legacy_arm(name: str) -> tuple[ReconConfig, dict]:
    """The frozen config of a legacy arm (``lab/arms/<name>.json``) and its trainer switches."""
    path = ARMS_DIR / f"{name}.json"
    try:
        fields, switches = legacy.split(json.loads(path.read_text())["recon"])
    except FileNotFoundError:
        raise SystemExit(f"arm {name!r}: no frozen config {path}") from None
    except (ValueError, KeyError) as e:
        raise SystemExit(f"arm {name!r}: {path}: {e}") from None
    return ReconConfig.model_validate(fields), switches


class LegacyArms(recon.Arms):
    """Today's arms and the legacy ones; the extra keys are the old trainer's switches."""

    def base(self, name: str) -> tuple[ReconConfig, dict]:
        if name in LEGACY_ARMS:
            return legacy_arm(name)
        return super().base(name)

    def split_sets(self, fields: dict) -> tuple[dict, dict]:
        return legacy.split(fields)

    def plugins(self, cfg: ReconConfig, extra: dict) -> dict:
        return legacy.plugins(cfg, extra)


arm = LegacyArms()  # arm("old") -> (its ReconConfig, its switches)


def arm_config(name: str) -> ReconConfig:
    """The ``ReconConfig`` of :data:`arm` ``name``."""
    return arm(name)[0]


def main(argv=None) -> int:
    return recon.main(argv, arms=arm, description=__doc__.split("\n")[0])


if __name__ == "__main__":
    raise SystemExit(main())
