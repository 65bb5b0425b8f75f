"""Hostile pickles for the server tests: each would create a canary file (or import a module that does)."""

from __future__ import annotations

import builtins
import codecs
import functools
import gzip
import importlib
import os
import pickle
import struct
import subprocess
from pathlib import Path

import numpy as np

try:
    from numpy._core.multiarray import _reconstruct
except ImportError:  # pragma: no cover - numpy < 2
    from numpy.core.multiarray import _reconstruct

__all__ = ["CANARY_MOD", "Reducer", "hostile_pickles"]

CANARY_MOD = "kitti_eval_server_canary_mod"


class Reducer:
    """Pickles as ``func(*args)`` (plus a state): the shape of every code-execution payload."""

    def __init__(self, func, args, state=None):
        self.func, self.args, self.state = func, args, state

    def __reduce__(self):
        return (self.func, self.args) if self.state is None else (self.func, self.args, self.state)


def _b(text: str) -> bytes:
    return text.encode()


def hostile_pickles(canary: Path, evil_npy: Path) -> dict[str, bytes]:
    """name -> pickle bytes; each would create ``canary`` (or import a module that does) if it ran."""
    cmd = f"touch {canary}"
    py = f"open({str(canary)!r}, 'w').close()"
    system = Reducer(os.system, (cmd,))
    mod = CANARY_MOD.encode()
    cases = {
        "os.system, protocol 2": pickle.dumps(system, protocol=2),
        "os.system, STACK_GLOBAL protocol 4": pickle.dumps(system, protocol=4),
        "os.system, hand-written protocol 0": _b(f"cos\nsystem\n(S'{cmd}'\ntR."),
        "posix.system, protocol 5": pickle.dumps(system, protocol=5),
        "subprocess.Popen": pickle.dumps(Reducer(subprocess.Popen, (["touch", str(canary)],)), protocol=2),
        "subprocess.check_output, hand-written": _b(f"csubprocess\ncheck_output\n((lp0\nS'touch'\naS'{canary}'\natR."),
        "builtins.eval": pickle.dumps(Reducer(eval, (py,)), protocol=2),
        "builtins.exec": pickle.dumps(Reducer(exec, (py,)), protocol=2),
        "builtins.open for writing": pickle.dumps(Reducer(builtins.open, (str(canary), "w")), protocol=2),
        "builtins.getattr(__import__('os'), 'system') chain": _b(
            f"cbuiltins\ngetattr\n(cbuiltins\n__import__\n(S'os'\ntRS'system'\ntR(S'{cmd}'\ntR."
        ),
        "__builtin__ (python 2 names) getattr chain": _b(
            f"c__builtin__\ngetattr\n(c__builtin__\n__import__\n(S'os'\ntRS'system'\ntR(S'{cmd}'\ntR."
        ),
        "functools.partial(os.system)": pickle.dumps(Reducer(functools.partial(os.system, cmd), ()), protocol=2),
        "importlib.import_module of a module that writes the canary": pickle.dumps(
            Reducer(importlib.import_module, (CANARY_MOD,)), protocol=2
        ),
        "GLOBAL of a module that writes the canary on import": b"c" + mod + b"\nrun\n)R.",
        "STACK_GLOBAL of a module that writes the canary on import": b"\x80\x04\x8c"
        + bytes([len(mod)])
        + mod
        + b"\x8c\x03run\x93)R.",
        "numpy.load of a pickled .npy with allow_pickle": pickle.dumps(
            Reducer(np.load, (str(evil_npy), None, True)), protocol=2
        ),
        "numpy.testing runstring (exec gadget)": _b(f'cnumpy.testing._private.utils\nrunstring\n(S"{py}"\n(dtR.'),
        "torch._utils._rebuild_tensor_v2, hand-written": b"\x80\x02ctorch._utils\n_rebuild_tensor_v2\nq\x00)Rq\x01.",
        "torch storage by persistent id": (
            b"\x80\x02(X\x07\x00\x00\x00storageq\x00ctorch\nFloatStorage\nX\x01\x00\x00\x000X\x03\x00\x00\x00cpuK"
            b"\x01tQ."
        ),
        "persistent id without a global (BINPERSID)": b"\x80\x02X\x03\x00\x00\x00keyQ.",
        "torch.storage._load_from_bytes": b"\x80\x02ctorch.storage\n_load_from_bytes\nC\x04abcd\x85R.",
        "os.system nested in a valid-looking result list": pickle.dumps(
            [{"frame_id": "000000", "name": np.array(["Car"]), "score": np.ones(1), "extra": [1, {"x": system}]}],
            protocol=2,
        ),
        "os.system inside an object array's state": pickle.dumps(
            Reducer(_reconstruct, (np.ndarray, (0,), b"b"), (1, (1,), np.dtype("O"), False, [system])), protocol=2
        ),
        "nested reduce: getattr on the result of a reduce": _b(
            f"cbuiltins\ngetattr\n(cos\npopen\n(S'{cmd}'\ntRS'read'\ntR)R."
        ),
        "memo: a memoized dtype called as a function": (
            b"\x80\x02cnumpy\ndtype\nq\x00X\x02\x00\x00\x00f8q\x01\x89\x88\x87q\x02Rq\x03h\x03(X\x01\x00\x00\x00xtR."
        ),
        "memo: GET of a slot never PUT": b"\x80\x02]q\x00h\x07a.",
        "memo: LONG_BINGET far out of range": b"\x80\x02]q\x00j\xff\xff\xff\x7fa.",
        "copyreg._reconstructor with subprocess.Popen": _b(
            "ccopy_reg\n_reconstructor\n(csubprocess\nPopen\nc__builtin__\nobject\nNtR."
        ),
        "operator.methodcaller('system') on __import__('os')": _b(
            f"coperator\nmethodcaller\n(S'system'\nS'{cmd}'\ntR(cbuiltins\n__import__\n(S'os'\ntRtR."
        ),
        "INST opcode (protocol 0 instance)": _b(f"(S'{cmd}'\nios\nsystem\n."),
        "OBJ opcode (protocol 1 instance)": _b(f"(cos\nsystem\nS'{cmd}'\no."),
        "NEWOBJ on an allowlisted class": b"\x80\x02cnumpy\nndarray\nK\x01\x85\x81.",
        "copyreg extension code (EXT1)": b"\x80\x02\x82\x01.",
        "pickle.loads of an inner payload": pickle.dumps(Reducer(pickle.loads, (pickle.dumps(system),)), protocol=2),
        "sys.modules": b"csys\nmodules\n.",
        "_codecs.encode as rot13": pickle.dumps(Reducer(codecs.encode, (py, "rot13")), protocol=2),
        "huge allocation: array shape 1e12 in the header": pickle.dumps(
            Reducer(_reconstruct, (np.ndarray, (10**12,), b"b")), protocol=2
        ),
        "huge allocation: shape 2**62 x 4 with an 8-byte buffer": pickle.dumps(
            Reducer(_reconstruct, (np.ndarray, (0,), b"b"), (1, (2**62, 4), np.dtype("f8"), False, b"\0" * 8)),
            protocol=2,
        ),
        "huge allocation: BINBYTES8 claiming 2**62 bytes": b"\x80\x04\x8e" + struct.pack("<Q", 2**62) + b"abc.",
        "huge allocation: one buffer reused as 300 arrays": pickle.dumps(
            [
                Reducer(_reconstruct, (np.ndarray, (0,), b"b"), (1, (1 << 17,), np.dtype("f8"), False, _SHARED))
                for _ in range(300)
            ],
            protocol=2,
        ),
        "huge allocation: bytearray(10**12)": pickle.dumps(Reducer(bytearray, (10**12,)), protocol=2),
        "deep nesting: 100k nested lists": b"\x80\x02" + b"]" * 100_000 + b"a" * 99_999 + b".",
        "deep nesting: tuple dict key 5000 deep": b"\x80\x02}K\x01" + b"\x85" * 5000 + b"K\x02s.",
        "structured dtype with fields outside the item": pickle.dumps(np.zeros(2, dtype=[("a", "<f8")]), protocol=2),
        "gzip-wrapped os.system": gzip.compress(pickle.dumps(system, protocol=2)),
    }
    return cases


_SHARED = b"\0" * (1 << 20)  # one 1 MB bytes object: pickle memoizes it, every array reuses it
