"""Frames in and out: frame sources (the interface every sensor, emulator, simulator and file replay
implements), frame files, file replay at a fixed rate, the newest-frame buffer and live recovery."""

from place_safe.io.frame_file import iter_frames, load_frames, write_frames
from place_safe.io.replay import FileReplaySource
from place_safe.io.source import FrameSource

__all__ = ["FrameSource", "FileReplaySource", "iter_frames", "load_frames", "write_frames"]
