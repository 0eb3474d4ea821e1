"""Would damping the flex rod's motion relative to its grippers help its fits? A probe, not a
backend feature: each calibrated flex rod (MuJoCo 4) gets, on every free vertex, a force
-rate * m * (v - v_ref), v_ref interpolated along the rod between the two pads' velocities
(a rigidly moving rod is not dragged; the -rate m v part is MuJoCo's implicit joint damping,
the rate m v_ref part an applied force), and replays the cable's eval recordings.

python examples/calibration/relative_damping_probe.py $DEFORM/DLO2 0,0.5,2,8 [air_damping=0.016]

prints the mean eval score (cm) per rate (1/s); rate 0 is the fit's own score.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import yaml

from dlocli.backends.mujoco_flex import MujocoFlex
from dlocli.calibration.fit import load_cable, replay_settings
from dlocli.calibration.replay import replay
from dlocli.calibration.spec import CalibrateSpec
from dlocli.specs import BackendSpec

HERE = Path(__file__).parent


class RelativelyDampedFlex(MujocoFlex):
    rate = 0.0  # 1/s

    def __init__(self, spec: BackendSpec, control_dt: float) -> None:
        super().__init__(spec, control_dt)
        m, layout = self.model, self.layout
        self._arc_fraction = np.array(
            [(i - layout.ghosts) / layout.n_segments for i in layout.free_vertices()]
        )[:, None]
        self._pad_dofs = [m.jnt_dofadr[m.joint(f"pad{p}").id] + np.arange(3) for p in range(2)]
        m.dof_damping[self._free_dofs] = self.rate * self._free_masses

    def _forced(self) -> bool:
        return True

    def _apply_forces(self) -> None:
        super()._apply_forces()
        d = self.data
        left, right = d.qvel[self._pad_dofs[0]], d.qvel[self._pad_dofs[1]]
        reference = (1 - self._arc_fraction) * left + self._arc_fraction * right
        d.qfrc_applied[self._free_dofs] += self.rate * self._free_masses * reference


def main(source: str, rates: str, *changes: str) -> None:
    cable_name = Path(source).name
    fields = yaml.safe_load((HERE / f"{cable_name}.yaml").read_text())
    spec = CalibrateSpec.model_validate({**fields, "source": source})
    fit = HERE / "results" / f"{cable_name}-mujoco-flex" / "calibrated.yaml"
    rod = yaml.safe_load(fit.read_text())["backend"]
    rod["rod"].update({k: float(v) for k, v in (c.split("=") for c in changes)})
    backend_spec = BackendSpec.model_validate(rod)
    spec.backend.name = backend_spec.name
    cable = load_cable(spec)
    settings = replay_settings(spec, cable.held)
    for rate in (float(r) for r in rates.split(",")):
        RelativelyDampedFlex.rate = rate
        backend = RelativelyDampedFlex(backend_spec, control_dt=1.0 / spec.rate_hz)
        runs = [replay(backend, rec, cable.arc, settings) for _, rec in cable.eval]
        score = np.mean([r.score_cm for r in runs])
        print(f"{cable_name} {changes} rate {rate:g}/s: eval {score:.4f} cm", flush=True)


if __name__ == "__main__":
    main(*sys.argv[1:])
