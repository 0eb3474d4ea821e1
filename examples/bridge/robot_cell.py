"""A cell of your own: the robot side of the dlocli-cell protocol in one short script.

    python examples/bridge/robot_cell.py --address tcp://0.0.0.0:5555
    dlo control --goal shape.npy --checkpoint runs/model --cell tcp://ROBOT:5555

It needs only pyzmq and numpy. Everything robot-specific is in `RobotCell`: replace its
methods with your robot's and your tracker's. As shipped, they drive dlocli's own MuJoCo rod
in this process, so the script runs as it is (and a controller cannot tell it from
`dlo serve`). The protocol is in the README ("A robot bridge").
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import zmq


class RobotCell:
    """Your robot and tracker. Units: metres, seconds, radians; world frame, z up."""

    def __init__(self, backend_spec: dict, control_dt: float) -> None:
        # --- replace: connect to your robot and your tracker here ---
        from dlocli.env.shape_env import make_backend
        from dlocli.specs import BackendSpec

        self.rod = make_backend(BackendSpec.model_validate(backend_spec), control_dt)

    def reset(self, seed: int | None, limits: dict) -> None:
        """Bring the grippers to the start pose and wait for the cable to settle; keep the
        grippers inside ``limits`` (workspace box, separation) from now on."""
        own = self.rod.limits
        own.low, own.high = np.array(limits["workspace_low"]), np.array(limits["workspace_high"])
        own.min_separation, own.max_separation = limits["min_separation"], limits["max_separation"]
        self.rod.reset(seed)

    def move(self, velocities: np.ndarray) -> None:
        """Send (2, 6) gripper twists (m/s, rad/s; left then right) for one control period."""
        self.rod.step(velocities)

    def stop(self) -> None:
        """Command zero velocity and hold the grippers where they are."""
        # a simulated rod only moves when stepped: nothing to do

    def observe(self) -> dict:
        """The tracked cable and the grippers, as the protocol's ``state`` fields."""
        return {
            "positions": self.rod.segment_positions().tolist(),
            "quaternions": self.rod.segment_quaternions().tolist(),
            "grippers": self.rod.gripper_poses().tolist(),
            "diverged": bool(self.rod.diverged),
        }


def serve(address: str) -> None:
    socket = zmq.Context().socket(zmq.REP)
    socket.bind(address)
    robot, steps = None, 0
    while True:
        request = json.loads(socket.recv())
        kind, reply = request["type"], {"type": "state"}
        if kind == "hello":
            robot = RobotCell(request["backend"], request["control_dt"])
            n_segments = request["backend"]["rod"]["n_segments"]
            reply = {
                "type": "welcome",
                "protocol": "dlocli-cell",
                "version": 1,
                "cell": {
                    "name": "robot",
                    "backend": request["backend"],
                    "realtime": False,
                    "control_dt": request["control_dt"],
                    "n_segments": n_segments,
                },
            }
        elif kind == "reset":
            robot.reset(request.get("seed"), request["limits"])
            steps = 0
        elif kind == "step":
            robot.move(np.array(request["velocities"]))
            steps += 1
        elif kind == "stop":
            robot.stop()
        elif kind == "bye":
            reply = {"type": "bye"}
        else:
            reply = {"type": "error", "message": f"this cell does not do {kind!r}"}
        if reply["type"] == "state":
            reply |= robot.observe() | {"step": steps, "late": 0, "dropped": 0}
        socket.send(json.dumps(reply).encode())


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--address", default="tcp://127.0.0.1:5555")
    serve(parser.parse_args().address)
