"""MCAP recording of ROS 2 topics without a ROS runtime: definitions, writer, reader.

The recorder and replay *nodes* (afm_bringup) only move bytes between DDS and these classes.
"""

from afm_core.recording.definitions import DefinitionNotFound, full_message_definition
from afm_core.recording.errors import RecordingError
from afm_core.recording.qos import QosDescription
from afm_core.recording.reader import DamagedChunk, RecordingReader, TopicInfo
from afm_core.recording.recover import Recovery, recover, recover_recording
from afm_core.recording.writer import RecordingWriter

__all__ = [
    "DamagedChunk",
    "DefinitionNotFound",
    "QosDescription",
    "RecordingError",
    "RecordingReader",
    "RecordingWriter",
    "Recovery",
    "TopicInfo",
    "full_message_definition",
    "recover",
    "recover_recording",
]
