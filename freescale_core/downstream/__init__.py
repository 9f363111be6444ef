"""Downstream consumers of free views (3DGS refinement, LVSM)."""
