"""Serve the project's deployments from this process (``prefect`` ``serve``).

``generate-dataset/local`` runs the main flow; run it with
``prefect deployment run 'generate-dataset/local' -p 'scenes=["path/to/scene"]' -p store=...``.
"""

from __future__ import annotations

from prefect import serve

from flows.generate_dataset import generate_dataset


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
    ]


if __name__ == "__main__":
    serve(*deployments())
