"""A tiny Robotiq URCap server on 127.0.0.1 for gripper tests (``SET`` -> ``ack``, ``GET VAR`` -> ``VAR n``)."""

from __future__ import annotations

import socket
import threading


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
