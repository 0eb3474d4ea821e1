"""Pickles of plain numbers, read within a memory budget.

A pickle is a program for a small machine; a recording is only lists (or tuples) of numbers.
Before anything is built, the program is read opcode by opcode (:mod:`pickletools`, which
builds nothing) and refused unless every opcode builds numbers or lists, no object is used
twice (a memo reference: how a few kilobytes fan out into gigabytes), every number fits in
a float, no object is stored in the memo at an index past what the pickle built so far
(the unpickler sizes its memo to the highest index: one opcode would take gigabytes), and
what loading builds fits the budget. Only then does pickle build it, with every global
(class, function) refused as well.
"""

from __future__ import annotations

import io
import pickle
import pickletools
import sys
from typing import Any

from dlocli.errors import BadInput

#: opcodes that build numbers, lists and tuples, or only frame and mark the stream
PLAIN = frozenset({
    "PROTO", "FRAME", "STOP", "MARK", "MEMOIZE", "PUT", "BINPUT", "LONG_BINPUT",
    "EMPTY_LIST", "LIST", "APPEND", "APPENDS",
    "EMPTY_TUPLE", "TUPLE", "TUPLE1", "TUPLE2", "TUPLE3",
    "FLOAT", "BINFLOAT", "INT", "BININT", "BININT1", "BININT2", "LONG", "LONG1", "LONG4",
})  # fmt: skip
NUMBERS = frozenset({"FLOAT", "BINFLOAT", "INT", "BININT", "BININT1", "BININT2", "LONG",
                     "LONG1", "LONG4"})  # fmt: skip
CONTAINERS = frozenset({"EMPTY_LIST", "LIST", "EMPTY_TUPLE", "TUPLE", "TUPLE1", "TUPLE2",
                        "TUPLE3"})  # fmt: skip
#: opcodes that store the object on top of the stack in the memo at the index they name
MEMO_PUTS = frozenset({"PUT", "BINPUT", "LONG_BINPUT"})
#: opcodes that name a class or function (module and name in the argument or the two texts
#: before it)
GLOBALS = frozenset({"GLOBAL", "STACK_GLOBAL", "INST"})
#: bytes loading takes per number: a Python float (24) and its list slot (8), then the
#: float64 array and its transposed copy (8 + 8)
BYTES_PER_NUMBER = 48
#: bytes per list or tuple: the object and its over-allocated slots
BYTES_PER_CONTAINER = 120
#: bytes per memo slot: the unpickler's table of pointers grows to twice the highest index
BYTES_PER_MEMO_SLOT = 16


class _NoGlobals(pickle.Unpickler):
    """An unpickler for plain data: every global (class, function) is refused."""

    def find_class(self, module: str, name: str) -> None:
        raise pickle.UnpicklingError(f"it names {module}.{name}")


def load_plain(data: bytes, name: str, budget_bytes: int) -> Any:
    """The lists of numbers pickled in ``data`` (the bytes of file ``name``); BadInput if it
    holds anything else or loading it would take more than ``budget_bytes`` of memory."""
    numbers, containers, memo_slots = _scan(data, name)
    needed = (len(data) + numbers * BYTES_PER_NUMBER + containers * BYTES_PER_CONTAINER
              + memo_slots * BYTES_PER_MEMO_SLOT)  # fmt: skip
    if needed > budget_bytes:
        raise BadInput(
            f"{name} would take {needed / 2**20:.0f} MiB to read ({numbers} numbers), over "
            f"the budget's {budget_bytes / 2**20:.0f} MiB left; raise --max-memory-mib or "
            "import fewer files"
        )
    try:
        return _NoGlobals(io.BytesIO(data)).load()  # shares data's memory
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, IndexError) as exc:
        raise BadInput(
            f"{name} is not a readable pickle ({type(exc).__name__}); re-download it"
        ) from exc


def _scan(data: bytes, name: str) -> tuple[int, int, int]:
    """(numbers, containers, memo slots) the pickle builds; BadInput at its first opcode that
    is not plain data (text is passed over to name the global it may spell, then refused)."""
    numbers = containers = highest_put = memoized = 0
    texts: list[str] = []
    try:
        for count, (opcode, arg, _) in enumerate(pickletools.genops(data)):
            if opcode.name in GLOBALS:
                spelled = arg.replace(" ", ".") if isinstance(arg, str) else ".".join(texts)
                raise _refused(name, f"it names {spelled}")
            if isinstance(arg, str) and opcode.name not in PLAIN:
                texts = [*texts[-1:], arg[:60]]
                continue
            if opcode.name not in PLAIN:
                raise _refused(name, f"it holds {opcode.name} (a {_kind(opcode.name)})")
            if opcode.name in NUMBERS:
                numbers += 1
                if isinstance(arg, int) and abs(arg) > sys.float_info.max:
                    raise _refused(name, f"it holds an integer of {arg.bit_length()} bits, too "
                                   "large for a float")  # fmt: skip
            containers += opcode.name in CONTAINERS
            memoized += opcode.name == "MEMOIZE"
            if opcode.name in MEMO_PUTS:
                if arg >= count:  # each object stored was built by an opcode before
                    raise _refused(name, f"it stores an object at memo index {arg}, past the "
                                   f"{count} opcodes before it (the memo would take "
                                   f"{arg * BYTES_PER_MEMO_SLOT / 2**20:.0f} MiB)")  # fmt: skip
                highest_put = max(highest_put, arg + 1)
    except (ValueError, EOFError) as exc:  # truncated, or a length past the end of the file
        raise BadInput(
            f"{name} is not a readable pickle ({str(exc)[:80]}); re-download it"
        ) from exc
    if texts:
        raise _refused(name, "it holds text")
    return numbers, containers, highest_put + memoized


def _kind(opcode: str) -> str:
    if opcode.endswith("GET"):
        return "second use of one object: a memo reference, how small pickles fan out"
    if opcode in {"REDUCE", "INST", "OBJ", "NEWOBJ", "NEWOBJ_EX", "BUILD"}:
        return "call, code a pickle can run"
    return "value other than numbers and lists"


def _refused(name: str, why: str) -> BadInput:
    return BadInput(
        f"{name} refused: {why} (only plain lists of numbers are loaded; code in a pickle is "
        "never run); pass the recording files"
    )
