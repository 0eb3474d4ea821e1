"""A depth camera's view of the cable and the tracker that turns it into ordered nodes.

:mod:`dlocli.tracking.camera` simulates the camera on any backend (its rays), the tracker
(:mod:`dlocli.tracking.tracker`) fits a chain of nodes to each frame's cloud and reads the
observation's markers off it, with a :class:`~dlocli.tracking.priors.NodePrior` predicting
the nodes it does not see.

The point-cloud observer registers here (:data:`dlocli.registry.observers`), so the env reaches
it by its observation kind without importing this package.
"""

from dlocli.registry import observers

observers.register(
    "pointcloud",
    "dlocli.tracking.observer:CloudObserver",
    "a depth camera on the backend and the cable tracker that reads the markers off its cloud",
)
