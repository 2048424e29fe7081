"""Evaluation of the detector and the pipeline against simulator ground truth."""
