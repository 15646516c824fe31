"""Grippers: the Robotiq URCap socket protocol against a local TCP server, and the digital output."""

from __future__ import annotations

import socket
import threading

import pytest

from place_safe.drivers.ur5.gripper import DigitalOutputGripper, RobotiqSocketGripper
from place_safe.exceptions import RobotFault


class FakeURCap:
    """A tiny Robotiq URCap server on 127.0.0.1: ``SET`` -> ``ack``, ``GET VAR`` -> ``VAR n``."""

    def __init__(self, fault: int = 0, garble: bool = False) -> None:
        self.state = {"ACT": 0, "GTO": 0, "POS": 0, "SPE": 0, "FOR": 0, "STA": 0, "OBJ": 3, "FLT": fault}
        self.lines: list[str] = []
        self.garble = garble
        self.srv = socket.create_server(("127.0.0.1", 0))
        self.port = self.srv.getsockname()[1]
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        conn, _ = self.srv.accept()
        with conn, conn.makefile("rw", newline="\n") as fh:
            for line in fh:
                cmd = line.strip()
                self.lines.append(cmd)
                parts = cmd.split()
                if parts[0] == "SET":
                    self.state[parts[1]] = int(parts[2])
                    if parts[1] == "ACT":
                        self.state["STA"] = 3
                    reply = "ack"
                elif parts[0] == "GET":
                    reply = "???" if self.garble else f"{parts[1]} {self.state[parts[1]]}"
                else:
                    reply = "nack"
                fh.write(reply + "\n")
                fh.flush()

    def close(self) -> None:
        self.srv.close()


def test_robotiq_activates_sets_speed_force_and_moves():
    srv = FakeURCap()
    g = RobotiqSocketGripper("127.0.0.1", srv.port, open_position=10, closed_position=230, speed=200, force=40,
                             sleep=lambda s: None)
    try:
        g.open()
        g.close()
    finally:
        g.close_connection()
        srv.close()
    sets = [ln for ln in srv.lines if ln.startswith("SET")]
    assert sets == ["SET ACT 1", "SET SPE 200", "SET FOR 40", "SET POS 10", "SET GTO 1", "SET POS 230", "SET GTO 1"]
    assert "GET OBJ" in srv.lines and "GET FLT" in srv.lines


@pytest.mark.parametrize("kwargs, match", [({"fault": 5}, "fault 5"), ({"garble": True}, "answered")])
def test_robotiq_faults_and_bad_replies_are_robot_faults(kwargs, match):
    srv = FakeURCap(**kwargs)
    g = RobotiqSocketGripper("127.0.0.1", srv.port, sleep=lambda s: None)
    try:
        with pytest.raises(RobotFault, match=match):
            g.open()
    finally:
        g.close_connection()
        srv.close()


def test_robotiq_unreachable_and_bad_values():
    s = socket.create_server(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    with pytest.raises(RobotFault, match="cannot connect"):
        RobotiqSocketGripper("127.0.0.1", port, timeout_s=0.5).open()
    with pytest.raises(ValueError):
        RobotiqSocketGripper("127.0.0.1", open_position=300)


def test_digital_output_gripper_levels():
    calls = []

    class IO:
        def setStandardDigitalOut(self, arg0, arg1):
            calls.append(("std", arg0, arg1))
            return True

        def setToolDigitalOut(self, arg0, arg1):
            calls.append(("tool", arg0, arg1))
            return False

    g = DigitalOutputGripper(IO(), output=3, open_level=False, settle_s=0.0)
    g.open()
    g.close()
    assert calls == [("std", 3, False), ("std", 3, True)]
    with pytest.raises(RobotFault, match="refused"):
        DigitalOutputGripper(IO(), 1, tool_output=True, settle_s=0.0).open()
