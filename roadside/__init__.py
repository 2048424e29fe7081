"""The `roadside` command: one entry point with a sub-command per job."""
