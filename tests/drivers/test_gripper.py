"""Grippers: the Robotiq URCap socket protocol against a local TCP server, and the digital output."""

from __future__ import annotations

import socket

import pytest
from urcap import FakeURCap

from place_safe.drivers.ur5.gripper import DigitalOutputGripper, RobotiqSocketGripper
from place_safe.exceptions import RobotFault


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
