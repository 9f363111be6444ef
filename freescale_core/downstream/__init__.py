"""Downstream uses of FreeScale data (METHOD.md "Downstream uses"): models trained on free views."""
