"""The robot bridge: a rod behind a socket (a served simulator or a robot with a tracker),
stepped through the dlocli-cell protocol (:mod:`dlocli.bridge.protocol`)."""
