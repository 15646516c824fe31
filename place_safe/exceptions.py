"""Errors raised by place_safe. Each message says what was wrong and what was expected."""


class PlaceSafeError(Exception):
    """Base class of every error place_safe raises on purpose."""


class FrameError(PlaceSafeError, ValueError):
    """A sensor frame is malformed: wrong shape, NaN or negative counts, missing reference."""


class FrameFileError(PlaceSafeError, ValueError):
    """A frame file cannot be read or does not follow docs/interfaces.md."""


class CalibrationError(PlaceSafeError, ValueError):
    """A calibration file or calibration data set is unusable."""


class NoPlaneError(PlaceSafeError):
    """No plane can be recovered from a frame (no return, saturated, not planar, bad data)."""


class SensorTimeout(PlaceSafeError, TimeoutError):
    """The sensor stopped answering within the allowed time."""


class RobotFault(PlaceSafeError, RuntimeError):
    """The robot reported a fault (protective stop, lost connection, limit violation)."""


class ConfigError(PlaceSafeError, ValueError):
    """A configuration file or value (robot, sensor, scenario, placement) is unusable."""


class SensorError(PlaceSafeError, RuntimeError):
    """The sensor failed in a way retries cannot fix (dead bus, wrong device, lost firmware)."""


class ArgumentTypeError(PlaceSafeError, TypeError):
    """A library function or constructor got an argument of the wrong type; the message says what it expected."""


class UsageError(PlaceSafeError):
    """Bad command-line usage (exit status 2). Defined here, not in the command line, so that every part that
    parses arguments (the ``place-safe`` commands, the simulation's sub-commands) raises the one class."""
