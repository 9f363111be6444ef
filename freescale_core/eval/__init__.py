"""Evaluation: metrics, the sample-scene oracle, sweeps."""
