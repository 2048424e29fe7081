"""fuse_track: Objects of every camera -> Tracks. The cores here know no transport: `ticks` groups
objects by capture time, `fusion` merges one tick's objects by camera region, `tracker` is SORT in
site metres."""
