"""A depth camera's view of the cable and the tracker that turns it into ordered nodes.

:mod:`dlocli.tracking.camera` simulates the camera on any backend (its rays), the tracker
(:mod:`dlocli.tracking.tracker`) fits a chain of nodes to each frame's cloud and reads the
observation's markers off it, with a :class:`~dlocli.tracking.priors.NodePrior` predicting
the nodes it does not see.
"""
