"""Detector training (needs the optional `train` extra: torch). Nothing here is imported by the services."""
