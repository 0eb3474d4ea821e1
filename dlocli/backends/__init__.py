"""Simulator backends: one module per simulator, all implementing :class:`Backend`.

The built-ins register here; each names its facts class (``dlocli.backends.facts``), so
specs and ``--help`` learn its limits without importing the simulator. Names are imported
lazily: importing this package imports no simulator.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from dlocli.extras import require
from dlocli.registry import backends, cells, import_target

if TYPE_CHECKING:
    from dlocli.backend_spec import BackendSpec
    from dlocli.backends.base import Backend
    from dlocli.cell_spec import CellChoice

backends.register(
    "mujoco",
    "dlocli.backends.mujoco_cable:MujocoCable",
    "MuJoCo 3.x composite cable (elasticity plugin), grippers as mocap bodies",
    facts="dlocli.backends.facts:MujocoFacts",
)
backends.register(
    "mujoco-flex",
    "dlocli.backends.mujoco_flex:MujocoFlex",
    "MuJoCo 4 flex rod (1D flex, discrete elastic rod with twist), grippers as welded pads",
    facts="dlocli.backends.facts:FlexFacts",
)
backends.register(
    "pybullet",
    "dlocli.backends.pybullet_chain:PybulletChain",
    "PyBullet chain of capsules, joint stiffness from EI/l and GJ/l",
    facts="dlocli.backends.facts:PybulletFacts",
)

#: the protocol of a cell (`dlo serve`, or a robot speaking it; dlocli.bridge.protocol.PROTOCOL):
#: its client, a backend reached by an address rather than picked by name, is registered under
#: it in :data:`dlocli.registry.cells` and imported when a run names a cell
CELL_PROTOCOL = "dlocli-cell"

_EXPORTS = {"Backend": "dlocli.backends.base", "GripperLimits": "dlocli.backends.base"}
__all__ = [*sorted(_EXPORTS), "make_backend", "runnable_backends"]


def make_backend(
    spec: BackendSpec, control_dt: float = 0.02, cell: CellChoice | None = None
) -> Backend:
    """Build the registered backend named by ``spec.name``, or, with ``cell.cell`` set, the
    rod of ``spec`` stepped by the cell at that address (the client of :data:`CELL_PROTOCOL`)."""
    if cell is not None and cell.cell is not None:
        require("bridge", "--cell", "drop --cell to simulate in this process")
        client = cells.get(CELL_PROTOCOL)
        return client(spec, control_dt, cell.cell, cell.cell_timeout_s, cell.cell_keys)
    return backends.get(spec.name)(spec, control_dt=control_dt)


def runnable_backends() -> list[str]:
    """The registered backends that run with the installed simulators (the composite cable
    needs MuJoCo 3, the flex rod MuJoCo 4); imports each one."""
    return [name for name in backends.names() if not backends.get(name).unavailable()]


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'dlocli.backends' has no attribute '{name}'")
    return import_target(f"{_EXPORTS[name]}:{name}")
