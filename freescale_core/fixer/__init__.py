"""A small image fixer the engine trains on its own leave-out renders (no external weights).

``data``: training pairs (render + warped nearby photos -> held-out photo); ``model``: the
network; ``infer``: batched inference; ``train``: cross-scene training. Making pairs from a
scene and scoring a fixer on a store need the whole engine, so they live in the top layer
(``eval.fixer_pairs``, ``eval.fixer_score``); the stage-10 backend is
``freeviews.rectify_image.FixerRectifier``.
"""
