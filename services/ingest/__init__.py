"""ingest: camera streams -> Frames."""
