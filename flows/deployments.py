"""Serve the project's deployments from this process (``prefect`` ``serve``).

``generate-dataset/local`` runs the main flow; run it with
``prefect deployment run 'generate-dataset/local' -p 'scenes=["path/to/scene"]' -p store=...``.
``refine-3dgs/local`` runs the 3DGS refinement comparison on a store made with
``recon_split=ood``. ``train-lvsm/local`` trains the LVSM view-synthesis model from packed shards
(``-p shards=data/shards``); started again on the same ``out`` it resumes from the checkpoint.
``train-fixer/local`` trains the fixer network from a pairs folder (``-p pairs=data/pairs
-p out=data/fixer -p 'holdout=["scene"]'``); it resumes a run in the same ``out``.
``evaluate-engine/local`` runs a speed-against-accuracy sweep (docs/EVALUATION.md):
``prefect deployment run 'evaluate-engine/local' -p 'scenes=["proc:tiny"]'``.
"""

from __future__ import annotations

from prefect import serve

from flows.evaluate_engine import evaluate_engine
from flows.generate_dataset import generate_dataset
from flows.refine_3dgs import refine_3dgs
from flows.make_fixer_pairs import make_fixer_pairs
from flows.train_fixer import train_fixer_flow
from flows.train_lvsm import train_lvsm_flow


def deployments():
    return [
        generate_dataset.to_deployment(
            name="local",
            description="Generate free views for scene folders into a store (threads).",
            parameters={"store": "data/store", "config": {"preset": "auto"}},
            tags=["freescale"],
        ),
        generate_dataset.to_deployment(
            name="local-dask",
            description="Same, scenes spread over a local Dask cluster on 127.0.0.1.",
            parameters={"store": "data/store", "config": {"preset": "auto"},
                        "scale_out": "dask"},
            tags=["freescale", "dask"],
        ),
        refine_3dgs.to_deployment(
            name="local",
            description="3DGS per scene with free views as pseudo ground truth, against the "
                        "captured-views baseline on held-out views (store made with "
                        "recon_split=ood).",
            parameters={"store": "data/store"},
            tags=["freescale", "downstream"],
        ),
        train_lvsm_flow.to_deployment(
            name="local",
            description="LVSM (feed-forward view synthesis) trained from packed shards, "
                        "held-out loss / PSNR, checkpoints; resumes a run in the same out.",
            parameters={"shards": "data/shards", "resume": True},
            tags=["freescale", "downstream"],
        ),
        make_fixer_pairs.to_deployment(
            name="local",
            description="Fixer training pairs for scene folders (leave-out renders, nearby "
                        "photos warped in, held-out photo as target); keeps folds already made.",
            parameters={"out": "data/pairs"},
            tags=["freescale", "fixer"],
        ),
        train_fixer_flow.to_deployment(
            name="local",
            description="The fixer network trained across scenes from engine-made pairs, "
                        "scenes held out by name; loss curve and before/after artifacts; "
                        "resumes a run in the same out.",
            parameters={"pairs": "data/pairs", "out": "data/fixer", "resume": True},
            tags=["freescale", "fixer"],
        ),
        evaluate_engine.to_deployment(
            name="local",
            description="Sweep named knobs over scenes: seconds per scene against accuracy, a "
                        "Pareto chart, sizing and stability tables (points cached).",
            parameters={"scenes": ["proc:tiny"], "out": "data/eval"},
            tags=["freescale", "evaluation"],
        ),
    ]


if __name__ == "__main__":
    serve(*deployments())
