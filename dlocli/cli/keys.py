"""`dlo keys`: CURVE keys for a cell off loopback and the controllers it lets in."""

from __future__ import annotations

from dlocli.bridge.keys import make_keys
from dlocli.bridge.spec import KeysSpec
from dlocli.cli.common import emit_summary, handle_errors
from dlocli.cli.flags import RunFlags, spec_flags
from dlocli.extras import require


@handle_errors
@spec_flags(KeysSpec)
def keys(
    run: RunFlags,
) -> None:
    """Make a key pair for a cell and one for its controller in a new folder (--out): serve
    with `dlo serve --keys DIR`, control with `dlo control --cell-keys DIR`. Secret files are
    readable by you only; the controller's machine needs controller.key_secret and cell.key."""
    spec = run.spec()
    require("bridge", "dlo keys")
    written = make_keys(spec.out)
    summary = {"out": str(spec.out), "files": [path.name for path in written]}
    emit_summary(summary, run.json, "dlo keys")
