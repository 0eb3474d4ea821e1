"""The robot bridge: a rod behind a socket (a served simulator or a robot with a tracker),
stepped through the dlocli-cell protocol (:mod:`dlocli.bridge.protocol`).

The protocol's client registers here (:data:`dlocli.registry.cells`), so a backend is built
for a cell's address without the backends importing this package.
"""

from dlocli.bridge.protocol import PROTOCOL
from dlocli.registry import cells

cells.register(
    PROTOCOL,
    "dlocli.bridge.remote:RemoteCell",
    "the REQ side of the dlocli-cell protocol: a served simulator or a robot behind a socket",
)
