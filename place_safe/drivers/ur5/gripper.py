"""Grippers on a UR5: a digital output (through ``rtde_io``) or a Robotiq 2F over the URCap's socket.

Concept: a :class:`Gripper` has ``open()``, ``close()`` and ``close_connection()``; the robot driver owns
one and never opens it on a fault. Two kinds:

* :class:`DigitalOutputGripper`: one standard or tool digital output of ``RTDEIOInterface``
  (``setStandardDigitalOut`` / ``setToolDigitalOut``), a level for "open", a settle time.
* :class:`RobotiqSocketGripper`: the Robotiq URCap's ASCII server on the controller (port 63352,
  newline-terminated commands ``SET ACT 1``, ``SET GTO 1``, ``SET POS n``, ``SET SPE n``, ``SET FOR n``
  answered ``ack``; ``GET POS``, ``GET STA``, ``GET OBJ``, ``GET FLT`` answered ``<VAR> <value>``).
  ``GET OBJ`` 1 or 2 means the fingers stopped on an object, 3 that they reached the position.

Every failure is a :class:`~place_safe.exceptions.RobotFault` with one line saying what failed.

Waiting: a gripper's waits (the digital gripper's settle, the Robotiq's polls and replies) go through its
``wait`` function; the robot driver binds its own (:meth:`Gripper.bind_wait`), which kicks the RTDE watchdog
every controller cycle -- a plain ``time.sleep`` there lets the 10 Hz watchdog stop the control script in the
middle of the release. With a bound wait the Robotiq socket is polled without blocking, one wait at a time.
"""

from __future__ import annotations

import select
import socket
import time
from abc import ABC, abstractmethod
from typing import Any, Callable

from place_safe.exceptions import RobotFault


class Gripper(ABC):
    @abstractmethod
    def open(self) -> None:
        """Release the held object (blocking until done)."""

    @abstractmethod
    def close(self) -> None:
        """Grip (blocking until the fingers stop)."""

    def close_connection(self) -> None:
        """Release resources (sockets). Idempotent."""

    def describe(self, open: bool) -> str:
        return f"{'open' if open else 'close'} gripper"

    def bind_wait(self, wait: Callable[[float], None]) -> None:
        """Wait with ``wait(seconds)`` from now on (the robot driver's, which services the watchdog)."""
        self._sleep = wait
        self._bound = True


class NoGripper(Gripper):
    def open(self) -> None:
        raise RobotFault("no gripper configured: cannot open")

    def close(self) -> None:
        raise RobotFault("no gripper configured: cannot close")


class DigitalOutputGripper(Gripper):
    """A gripper on one digital output of ``rtde_io.RTDEIOInterface``."""

    def __init__(self, io: Any, output: int = 0, tool_output: bool = False, open_level: bool = True,
                 settle_s: float = 0.3, sleep: Callable[[float], None] = time.sleep) -> None:
        self.io, self.output, self.tool_output, self.open_level = io, int(output), bool(tool_output), bool(open_level)
        self.settle_s, self._sleep = float(settle_s), sleep
        self._bound = False

    def _set(self, level: bool) -> None:
        fn = self.io.setToolDigitalOut if self.tool_output else self.io.setStandardDigitalOut
        try:
            ok = fn(self.output, level)
        except RuntimeError as exc:
            raise RobotFault(f"gripper output {self.output}: {exc}") from None
        if ok is False:
            raise RobotFault(f"gripper output {self.output}: the controller refused to set it to {level}")
        if self.settle_s:
            self._sleep(self.settle_s)

    def open(self) -> None:
        self._set(self.open_level)

    def close(self) -> None:
        self._set(not self.open_level)

    def describe(self, open: bool) -> str:
        kind = "tool" if self.tool_output else "standard"
        level = self.open_level if open else not self.open_level
        return f"{kind} digital output {self.output} -> {level} ({'open' if open else 'close'} gripper)"


class RobotiqSocketGripper(Gripper):
    """A Robotiq 2F gripper through the URCap socket (see the module docstring)."""

    def __init__(self, host: str, port: int = 63352, open_position: int = 0, closed_position: int = 255,
                 speed: int = 128, force: int = 64, timeout_s: float = 2.0,
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep) -> None:
        for name, v in (("open_position", open_position), ("closed_position", closed_position),
                        ("speed", speed), ("force", force)):
            if not (isinstance(v, int) and 0 <= v <= 255):
                raise ValueError(f"Robotiq {name} must be an integer 0..255; got {v!r}")
        self.host, self.port = host, int(port)
        self.open_position, self.closed_position = open_position, closed_position
        self.speed, self.force, self.timeout_s = speed, force, float(timeout_s)
        self._clock, self._sleep = clock, sleep
        self._bound = False
        self._sock: socket.socket | None = None
        self._buf = b""

    # -- protocol ---------------------------------------------------------------------------------
    def connect(self) -> None:
        if self._sock is not None:
            return
        try:
            self._sock = socket.create_connection((self.host, self.port), timeout=self.timeout_s)
        except OSError as exc:
            raise RobotFault(f"Robotiq gripper at {self.host}:{self.port}: cannot connect ({exc})") from None
        self._buf = b""
        if self.get("STA") != 3:  # 3 = activation completed
            self._command("SET ACT 1")
            deadline = self._clock() + max(self.timeout_s, 5.0)
            while self.get("STA") != 3:
                if self._clock() > deadline:
                    raise RobotFault("Robotiq gripper did not finish activating")
                self._sleep(0.05)
        self._command(f"SET SPE {self.speed}")
        self._command(f"SET FOR {self.force}")

    def _line(self) -> str:
        assert self._sock is not None
        deadline = self._clock() + self.timeout_s
        while b"\n" not in self._buf:
            if self._bound:  # poll, waiting with the robot's wait (watchdog kicked) in between
                try:
                    ready = select.select([self._sock], [], [], 0.0)[0]
                except (OSError, ValueError) as exc:
                    raise RobotFault(f"Robotiq gripper: no reply ({exc})") from None
                if not ready:
                    if self._clock() > deadline:
                        raise RobotFault(f"Robotiq gripper: no reply within {self.timeout_s:g} s")
                    self._sleep(0.008)
                    continue
            try:
                chunk = self._sock.recv(1024)
            except OSError as exc:
                raise RobotFault(f"Robotiq gripper: no reply ({exc})") from None
            if not chunk:
                raise RobotFault("Robotiq gripper: connection closed by the controller")
            self._buf += chunk
        line, self._buf = self._buf.split(b"\n", 1)
        return line.decode("ascii", "replace").strip()

    def _send(self, text: str) -> str:
        self.connect()
        assert self._sock is not None
        try:
            self._sock.sendall((text + "\n").encode("ascii"))
        except OSError as exc:
            raise RobotFault(f"Robotiq gripper: cannot send {text!r} ({exc})") from None
        return self._line()

    def _command(self, text: str) -> None:
        reply = self._send(text)
        if reply != "ack":
            raise RobotFault(f"Robotiq gripper: {text!r} answered {reply!r}, expected 'ack'")

    def get(self, var: str) -> int:
        reply = self._send(f"GET {var}")
        parts = reply.split()
        if len(parts) != 2 or parts[0] != var or not parts[1].lstrip("-").isdigit():
            raise RobotFault(f"Robotiq gripper: GET {var} answered {reply!r}, expected '{var} <number>'")
        return int(parts[1])

    def move(self, position: int) -> int:
        """Go to ``position`` (0..255) and wait until the fingers stop; returns the final OBJ status."""
        self._command(f"SET POS {int(position)}")
        self._command("SET GTO 1")
        deadline = self._clock() + self.timeout_s
        while True:
            flt = self.get("FLT")
            if flt != 0:
                raise RobotFault(f"Robotiq gripper fault {flt} while moving to {position}")
            obj = self.get("OBJ")
            if obj in (1, 2, 3):
                return obj
            if self._clock() > deadline:
                raise RobotFault(f"Robotiq gripper did not stop within {self.timeout_s:g} s (moving to {position})")
            self._sleep(0.02)

    def open(self) -> None:
        self.move(self.open_position)

    def close(self) -> None:
        self.move(self.closed_position)

    def close_connection(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            finally:
                self._sock = None

    def describe(self, open: bool) -> str:
        pos = self.open_position if open else self.closed_position
        return f"Robotiq {self.host}:{self.port} SET POS {pos}, SET GTO 1 ({'open' if open else 'close'} gripper)"


def make_gripper(cfg: Any, host: str, io: Any) -> Gripper:
    """The gripper a :class:`~place_safe.drivers.ur5.config.URConfig` ``gripper`` section describes."""
    if cfg.kind == "digital":
        return DigitalOutputGripper(io, cfg.output, cfg.tool_output, cfg.open_level, cfg.settle_s)
    if cfg.kind == "robotiq":
        return RobotiqSocketGripper(cfg.host or host, cfg.port, cfg.open_position, cfg.closed_position,
                                    cfg.speed, cfg.force, cfg.timeout_s)
    return NoGripper()


__all__ = ["Gripper", "NoGripper", "DigitalOutputGripper", "RobotiqSocketGripper", "make_gripper"]
