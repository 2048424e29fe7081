"""The project's common package: geo frames, camera models, ground model (and later the wire contract)."""
