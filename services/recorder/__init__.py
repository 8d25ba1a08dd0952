"""Recorder: every message of a rig to MCAP (JSON with schemas, Foxglove-ready), and back.

`schema` turns messages into MCAP JSON records and JSON Schemas, `writer` decides the files (per
run, rolling idle, rotation, chunking, disk errors), `reading` reads them back (with recovery of
truncated files), summarises runs and times replays; `node` wires recording and replay to Zenoh.
"""

from bagit.services.recorder.reading import Record, Recording, file_summary, list_runs, read_messages, replay_offsets
from bagit.services.recorder.schema import from_json, json_schema_bytes, schema_name, to_json
from bagit.services.recorder.writer import RecorderConfig, RecordingWriter

__all__ = [
    "Record", "Recording", "file_summary", "list_runs", "read_messages", "replay_offsets",
    "from_json", "json_schema_bytes", "schema_name", "to_json", "RecorderConfig", "RecordingWriter",
]
