"""Rerun sink: Tracks messages (and optionally camera frames) -> a Rerun recording (.rrd file or live viewer).

Rerun lives only here, at the edge: the pipeline's cores never import it. Every function takes an explicit
`rr.RecordingStream` or makes its own; importing this package logs nothing.
"""

from shared.tracks_file import TrackRow, TracksMessage, parse_tracks_message

from .basemap import Basemap
from .sink import TrackSink, live, track_color, tracks_file_to_rrd

__all__ = [
    "Basemap",
    "TrackRow",
    "TrackSink",
    "TracksMessage",
    "live",
    "parse_tracks_message",
    "track_color",
    "tracks_file_to_rrd",
]
