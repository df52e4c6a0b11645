"""Accuracy studies: ``python -m experiments.studies.speed_vs_accuracy`` (stability, compare_filters, reference_check)."""
