"""A small image fixer the engine trains on its own leave-out renders (no external weights).

``data``: training pairs (render + warped nearby photos -> held-out photo);
``pairs``: making them from a scene; ``model``: the network; ``train``: cross-scene training.
"""
