"""LVSM novel-view synthesis trained on captured + free views.

Modules: ``model`` (the decoder-only LVSM transformer, Plücker rays, pose normalisation, loss)
and ``sampler`` (which views form one training example: frame and view-graph branches with a
curriculum shared with DataLoader workers). Import them directly; nothing is re-exported here.
"""
