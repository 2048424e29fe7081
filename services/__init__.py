"""The four services of the live pipeline (ingest -> detect -> localize -> fuse_track) and the Rerun sink.
Each runs as `python -m services.<name> --site SITE`; they share only the contract in `shared/`."""
