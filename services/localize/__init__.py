"""localize: Detections -> Objects (lookup masks)."""
