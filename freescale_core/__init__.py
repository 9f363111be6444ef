"""FreeScale: certainty-aware free-view generation for 3D vision data.

One module per pipeline stage; each is a pure function from typed inputs to typed
outputs. ``tasks/`` wraps them for Prefect and ``flows/`` orders the tasks.
"""

__version__ = "0.1.0"
