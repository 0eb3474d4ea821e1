"""A cell of your own: the robot side of the dlocli-cell protocol in one short script.

    python examples/bridge/robot_cell.py --address tcp://127.0.0.1:5555
    dlo control --goal shape.npy --checkpoint runs/model --cell tcp://127.0.0.1:5555

    dlo keys --out keys                        # off loopback: keys for both sides
    python examples/bridge/robot_cell.py --address tcp://0.0.0.0:5555 --keys keys
    dlo control --goal shape.npy --checkpoint runs/model --cell tcp://ROBOT:5555 --cell-keys keys

Everything robot-specific is in `RobotCell`: replace its methods with your robot's and your
tracker's. As shipped, they drive dlocli's own MuJoCo rod in this process, so the script runs
as it is (and a controller cannot tell it from `dlo serve`). Every request is checked, and one
controller at a time owns the cell, by dlocli's own server (`dlocli.bridge.server`) before
your methods run: a bad or foreign request gets an error and never reaches the robot. The
protocol is in docs/real-cell.md ("A robot bridge").
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from dlocli.bridge.robot import Robot
from dlocli.bridge.server import Listening, Logged, serve
from dlocli.errors import BadInput
from dlocli.events import Event


class RobotCell(Robot):
    """Your robot and tracker. Units: metres, seconds, radians; world frame, z up."""

    name = "robot"
    reset_timeout_s = 30.0  # a real robot moves to its start pose and lets the cable settle

    def __init__(self) -> None:
        # --- replace: connect to your robot and your tracker here (before the cell listens) ---
        from dlocli.env.shape_env import make_backend
        from dlocli.specs import BackendSpec

        spec, control_dt = BackendSpec(), 0.02  # the rod dlocli's default controller brings
        self.rod = make_backend(spec, control_dt)
        # a real robot passes backend=None: any controller of n_segments nodes may drive it
        super().__init__(spec.rod.n_segments, control_dt, backend=spec.model_dump(mode="json"))

    def reset(self, seed, limits) -> None:
        """Bring the grippers to the start pose and wait for the cable to settle; keep the
        grippers inside ``limits`` (workspace box, separation) from now on."""
        if limits is not None:
            own = self.rod.limits
            own.low, own.high = np.array(limits.workspace_low), np.array(limits.workspace_high)
            own.min_separation, own.max_separation = limits.min_separation, limits.max_separation
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
            "positions": self.rod.segment_positions(),
            "quaternions": self.rod.segment_quaternions(),
            "grippers": self.rod.gripper_poses(),
            "diverged": self.rod.diverged,
        }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--address", default="tcp://127.0.0.1:5555")
    parser.add_argument("--keys", type=Path, help="a `dlo keys` folder; required off loopback")
    args = parser.parse_args()
    robot = RobotCell()  # what is slow happens before the cell listens

    def say(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    def report(event: Event) -> None:  # what the server does: where it listens, then its log
        if isinstance(event, Listening):
            say(f"serving at {event.address}; Ctrl-C stops")
        elif isinstance(event, Logged):
            say(event.line)

    try:
        serve(robot, args.address, args.keys, progress=report)
    except BadInput as exc:  # an address off loopback without keys, keys that do not load
        say(f"error: {exc}")
        sys.exit(2)
    except KeyboardInterrupt:
        say("stopped")


if __name__ == "__main__":
    main()
