"""The check behind :func:`kitti_eval.io.safe_pickle.load_pickle`: a model of CPython's C unpickler over types.

:func:`scan` reads a pickle (protocols 0-5) opcode by opcode, exactly as ``_pickle.c`` frames it, and keeps
for every value only what the checks need: its kind, an int's value, where a str or bytes lies and how long
it is, a tuple's children, a list's length, an array's dtype, a container's nesting depth. It runs over the
whole input before the C unpickler sees a byte, and accepts the pickle only if every call, every BUILD and
every container operation the C unpickler would perform is an allowed one:

* globals only from the allowlist, and only ever called (REDUCE) or passed as the subtype of
  ``_reconstruct``, never a value;
* REDUCE with the arguments numpy writes: ``_reconstruct(ndarray, (0,), b"b")``; ``dtype(code, bool,
  True)`` for a plain numeric, str, bytes or object code; ``scalar(complete non-object dtype, bytes of its
  itemsize)``; ``_frombuffer(bytes, complete non-object dtype, shape, order[, axis order])`` with exactly
  ``prod(shape) * itemsize`` bytes; ``_codecs.encode(str, latin-1)``; ``OrderedDict()``; ``bytes()``;
* BUILD once, on a fresh array not yet in a container (state ``(1, shape, complete dtype, bool, data)`` with exactly
  ``prod(shape) * itemsize`` bytes, or for object arrays a list of exactly ``prod(shape)`` str, numbers,
  bytes, None or numpy scalars) or on a fresh dtype (exactly the canonical state of a plain dtype: numpy's
  own ``__setstate__`` accepts states that read or free arbitrary memory later);
* APPEND(S) only on lists, SETITEM(S) only on dicts, ADDITEMS only on sets, and never on a container that
  is already inside another one (so there are no cycles and depths are final when computed); dict keys
  and set members hashable;
* nesting at most ``max_depth`` deep (CPython's tuple hash recurses in C without a guard) and at most
  ``key_budget`` elements of tuple keys hashed in all (a shared-child tuple DAG would hash for ever; str
  and number keys are cheap and do not count);
* what the C unpickler will hold and what a reader will make of it -- array bytes (counted at every BUILD,
  call and encode, shared inputs each time; an array of numbers at 8 bytes an element at least, as a reader
  converts it to float64), 32 bytes an object, 24 an item put into a container, 8 a stack slot -- within
  ``budget`` (a small pickle cannot make a huge array, nor millions of empty containers or dict entries);
  a value put into a container a second time (the memo, DUP) is charged the array bytes it holds again,
  each time, since a reader copies it once a place (a small pickle whose frames all share one big array
  cannot expand to a huge set of boxes); the strings of all its str arrays, at the widest one's width (a
  reader joins the frames' class names into one array of that width), within ``budget`` too; memo indices
  within the number of memo writes + 1024
  (``_pickle.c`` sizes its memo array by the largest index);
* no NEWOBJ(_EX), INST, OBJ, EXT1/2/4, (BIN)PERSID, NEXT_BUFFER, READONLY_BUFFER.

Where ``_pickle.c`` is lenient the scan is stricter; it never accepts what the C unpickler would read
differently. It needs no GIL and runs as plain Python too (``NUMBA_DISABLE_JIT=1``), only slower.
"""

from __future__ import annotations

import numpy as np

from ..core.kernel_cache import njit

# ------------------------------------------------------------------------------------------ error codes
OK = 0
# not a readable pickle (InputError)
E_TRUNC = 1  # the data ends inside an opcode or before STOP
E_OPCODE = 2  # unknown opcode (i0: the byte)
E_UNDERFLOW = 3  # stack underflow, or an object taken across a MARK
E_NOMARK = 4  # an opcode needs a MARK that is not there
E_BADARG = 5  # a malformed opcode argument
E_MEMO = 6  # GET of an empty memo slot (i0: index)
E_MEMO_RANGE = 7  # memo index far beyond the number of memo writes (i0: index)
E_ODD = 8  # odd number of items for DICT / SETITEMS
E_DEPTH = 9  # nested more than max_depth deep
E_KEYS = 10  # more than key_budget tuple elements hashed
E_UNHASHABLE = 11  # dict key or set item that cannot be hashed (i0: node)
E_CHANGED = 12  # a container changed after it was put into another one
E_BUDGET = 13  # more bytes built (array data, objects, the stack) than the budget (i0: bytes charged, i1: of them
# charged again for values put into containers more than once)
E_OOB = 14  # out-of-band buffers
E_NOT_TUPLE = 15  # REDUCE arguments that are not a tuple
E_HEADER = 16  # _reconstruct arguments other than numpy's empty int8 shell
E_SHAPE = 17  # a shape that is not a tuple of at most 64 sizes >= 0
E_SIZE = 18  # data bytes differ from prod(shape) * itemsize (i0: shape, i1: dtype, i2: bytes)
E_LIST = 19  # object array state with a list of the wrong length (i1: shape)
E_ARRSTATE = 20  # array state that is not (1, shape, dtype, fortran, data)
E_INCOMPLETE = 21  # a dtype used before its state was set
E_RAWTYPE = 22  # array data of the wrong type, or of a size the scan cannot know
E_ORDER = 23  # bad order, axis order or fortran flag
E_SCALAR = 24  # numpy scalar data of the wrong size or type
E_FROMBUF_OBJ = 25  # object dtype from a raw buffer
E_DTYPE_SIZE = 26  # bad str/bytes size in a dtype state (i1: size)
E_ARGS = 27  # wrong number or kind of call arguments
E_WIDE = 29  # str arrays that, read together at the widest one's width, take more than the budget (i0: strings,
# i1: the widest one's itemsize)
E_ROOM = 28  # not an error: work array i0 (a ROOM_* index) needs i1 rows; the caller grows it and calls again
ROOM_NODES, ROOM_CH, ROOM_STACK, ROOM_MARKS, ROOM_MEMO, ROOM_ITEMS = range(6)
# refused (UnsafePickleError)
E_GLOBAL = 40  # a global outside the allowlist (i0: 0 GLOBAL, i1/i2 line offsets; 1 STACK_GLOBAL, str nodes)
E_NEWOBJ = 41
E_INST = 42
E_EXT = 43
E_PERSID = 44
E_CALL = 45  # REDUCE on something that is not an allowlisted callable (i0: node)
E_BUILD = 46  # BUILD on something other than a fresh array or dtype (i0: node)
E_GLOBAL_VALUE = 47  # a global used as a value (i0: node)
E_DTYPE_CODE = 48  # numpy.dtype code not accepted (i0: node of the code)
E_DTYPE_STATE = 49  # dtype state other than the canonical plain state
E_SUBTYPE = 50  # _reconstruct of something other than numpy.ndarray (i0: node)
E_OBJ_ITEMS = 51  # object array holding something other than str, numbers, bytes, None
E_ENCODE = 52  # _codecs.encode other than str -> latin-1
E_ODICT_ARGS = 53
E_BYTES_ARGS = 54
E_SCALAR_OBJ = 55  # numpy scalar of object dtype
E_NOT_DTYPE = 56  # something other than a dtype where numpy expects one
E_TARGET = 57  # APPENDS / SETITEMS / ADDITEMS on an object of the wrong kind (i0: node)
E_DTYPE_ARGS = 58  # numpy.dtype called other than (code, align: bool, copy=True)

# ------------------------------------------------------------------------------------------ node kinds
K_NONE = 1
K_INT = 2  # V: the value (bools have F_BOOL)
K_BIGINT = 3  # an int whose value the scan does not know
K_FLOAT = 4
K_STR = 5  # raw bytes data[A:A+B]; V chars (-1: unknown); F_CONTENT: the raw bytes are the ASCII text
K_BYTES = 6  # V bytes (-1: unknown); F_CONTENT: data[A:A+V] are the bytes
K_BYTEARRAY = 7  # V bytes
K_TUPLE = 8  # children ch[A:A+B]; V: elements hashed when it is a key
K_LIST = 9  # V items
K_DICT = 10
K_SET = 11
K_FROZENSET = 12
K_ODICT = 13
K_GLOBAL = 14  # V: row of the allowlist
K_SHELL = 15  # numpy array from _reconstruct; F_BUILT once its state is set, A: then its state's node
K_ARRAY = 16  # numpy array from _frombuffer
K_DTYPE = 17  # V itemsize (-1 until known), A kind letter, B dtype-table row; F_BUILT once its state is set,
# F_BIG when that state is big-endian
K_SCALAR = 18  # A: the node of its arguments (dtype, bytes)

KIND_NAMES = {
    K_NONE: "None",
    K_INT: "int",
    K_BIGINT: "int",
    K_FLOAT: "float",
    K_STR: "str",
    K_BYTES: "bytes",
    K_BYTEARRAY: "bytearray",
    K_TUPLE: "tuple",
    K_LIST: "list",
    K_DICT: "dict",
    K_SET: "set",
    K_FROZENSET: "frozenset",
    K_ODICT: "OrderedDict",
    K_GLOBAL: "global",
    K_SHELL: "numpy array",
    K_ARRAY: "numpy array",
    K_DTYPE: "numpy dtype",
    K_SCALAR: "numpy scalar",
}

# a node is a row of 6 int64: W = kind | flags | opcode << 24 | depth << 32, then V, A, B (per kind, above), and
# X: the bytes of array data the value holds (an array's own, a container's items' summed, each time one is in it),
# S: the same of the elements of str arrays
W = 0
V = 1
A = 2
B = 3
X = 4
S = 5
COLUMNS = 6
KIND_MASK = 0xFF
OP_SHIFT = 24
DEPTH_SHIFT = 32
F_PLACED = 1 << 8  # inside a container: frozen from then on (a list, dict or set), charged again when put in another
F_GLOBALISH = 1 << 9  # a global, or a tuple holding one
F_BUILT = 1 << 10
F_BOOL = 1 << 11
F_CONTENT = 1 << 12
F_LEAVES = 1 << 13  # list: every item may go into an object array
F_UNHASHABLE = 1 << 14  # tuple: holds something unhashable
F_BIG = 1 << 15  # dtype: its state says big-endian ('>')

# what each allowlisted global does (column 4 of the globals table)
FN_RECONSTRUCT = 1
FN_FROMBUFFER = 2
FN_NDARRAY = 3
FN_DTYPE = 4
FN_SCALAR = 5
FN_ENCODE = 6
FN_ODICT = 7
FN_BYTES = 8

# dtype table columns (rows made by safe_pickle from numpy itself)
D_OFF = 0  # the code in the blob
D_LEN = 1
D_KIND = 2  # kind letter
D_ITEMSIZE = 3  # -1 for U and S (the state gives it)
D_BO = 4  # allowed byte orders: bit 0 '<', 1 '>', 2 '|'
D_ELSIZE = 5  # the canonical state's elsize, alignment and flags (elsize -1 for fixed sizes)
D_ALIGN = 6
D_FLAGS = 7

_LEAVES = (
    (1 << K_NONE) | (1 << K_INT) | (1 << K_BIGINT) | (1 << K_FLOAT) | (1 << K_STR) | (1 << K_BYTES) | (1 << K_SCALAR)
)
_HASHABLE = _LEAVES | (1 << K_TUPLE) | (1 << K_FROZENSET) | (1 << K_DTYPE)
_MUTABLE = (1 << K_LIST) | (1 << K_DICT) | (1 << K_SET) | (1 << K_ODICT)
_NONE, _TRUE, _FALSE, _FLOAT, _BIGINT, _INT0 = 0, 1, 2, 3, 4, 5  # shared nodes; _INT0 + i is the int i < 256
_FIRST = _INT0 + 256
_SAT = 1 << 62
_OBJECT_BYTES = 32  # what the budget charges for each object the C unpickler makes (an empty dict is 80)
_ITEM_BYTES = 24  # ... and for each item put into a container (a dict takes 30-50 bytes an entry, a list 8 an item)
_MAX_DIMS = 64


def _table(*groups: tuple[bytes, int]) -> np.ndarray:
    """A 256-entry lookup by opcode byte (numba keeps module-level arrays as constants)."""
    t = np.zeros(256, np.int64)
    for ops, value in groups:
        t[list(ops)] = value
    return t


_FIXED = _table((b"Khq\x80\x8a", 1), (b"M", 2), (b"Jjr\x8b", 4), (b"G\x95", 8))  # argument bytes
_COUNTED = _table((b"UC\x8c", 1), (b"TBX", 4), (b"\x8d\x8e\x96", 8))  # bytes of the length before the data
_LINES = _table((b"FILSVgp", 1), (b"c", 2))  # newline-terminated arguments
_REFUSED = _table(
    (b"PQ", E_PERSID), (b"\x82\x83\x84", E_EXT), (b"io", E_INST), (b"\x81\x92", E_NEWOBJ), (b"\x97\x98", E_OOB)
)
_NEW = _table(
    (b"UTXSV\x8c\x8d", K_STR),
    (b"CB\x8e", K_BYTES | F_CONTENT),
    (b"\x96", K_BYTEARRAY),
    (b")t\x85\x86\x87", K_TUPLE),
    (b"]l", K_LIST | F_LEAVES),
    (b"}d", K_DICT),
    (b"\x8f", K_SET),
    (b"\x91", K_FROZENSET),
)  # what a value or container opcode makes
_FROM_MARK = _table((b"tldu\x91e\x90", 1))  # takes the items above the last MARK
_INTO = _table((b"ae", K_LIST), (b"su", K_DICT), (b"\x90", K_SET))  # adds items to the container below them
BASE_NODES = np.zeros((_FIRST, COLUMNS), np.int64)  # the shared nodes: None, True, False, a float, an int, 0..255
BASE_NODES[:, W] = K_INT
BASE_NODES[[_NONE, _FLOAT, _BIGINT], W] = [K_NONE, K_FLOAT, K_BIGINT]
BASE_NODES[[_TRUE, _FALSE], W] |= F_BOOL
BASE_NODES[_TRUE, V] = 1
BASE_NODES[_INT0:, V] = np.arange(256)


@njit(cache=True, nogil=True)
def _uint(data, p, n):
    """Unsigned little-endian int of n <= 8 bytes; -1 if it does not fit in 63 bits."""
    if n == 8 and data[p + 7] >= 128:
        return -1
    x = 0
    for i in range(n):
        x |= int(data[p + i]) << (8 * i)
    return x


@njit(cache=True, nogil=True)
def _line_end(data, p):
    for i in range(p, data.shape[0]):
        if data[i] == 10:
            return i
    return -1


@njit(cache=True, nogil=True)
def _decimal(data, p, e):
    """(ok, value) of a strict decimal int in data[p:e]: '-'? digits, no leading zero, at most 18 digits."""
    neg = p < e and data[p] == 45
    p += int(neg)
    if not 1 <= e - p <= 18 or (data[p] == 48 and (e - p > 1 or neg)):
        return False, 0
    v = 0
    for i in range(p, e):
        if not 48 <= data[i] <= 57:
            return False, 0
        v = v * 10 + int(data[i]) - 48
    return True, -v if neg else v


@njit(cache=True, nogil=True)
def _memo_index(data, pos, fixed, line):
    """(memo index, position after it) of a GET/PUT-family argument: ``fixed`` little-endian bytes, or a
    line of digits; the index is -1 when the line is anything else."""
    if fixed:
        return _uint(data, pos, fixed), pos + fixed
    idx = -1 if line == pos or line - pos > 18 else 0
    for i in range(pos, line if idx == 0 else pos):
        if not 48 <= data[i] <= 57:
            return -1, line + 1
        idx = idx * 10 + int(data[i]) - 48
    return idx, line + 1


@njit(cache=True, nogil=True)
def _equals(data, p, n, blob, q, m):
    if n != m:
        return False
    for i in range(n):
        if data[p + i] != blob[q + i]:
            return False
    return True


@njit(cache=True, nogil=True)
def _text(data, p, n, op):
    """(chars, content) of a str opcode's raw bytes: the number of characters (-1 if unknown) and whether the
    raw bytes are the ASCII text itself. UNICODE is raw-unicode-escape (a backslash run of odd length then
    u/U starts one escaped character), STRING is quoted with escapes, the binary ones UTF-8 or ASCII."""
    ascii_ = True
    slash = False
    for i in range(p, p + n):
        ascii_ = ascii_ and data[i] < 128
        slash = slash or data[i] == 92
    if op == 83:  # STRING
        return (n if not slash else -1), ascii_ and not slash
    if op != 86:  # UTF-8 (binary unicode) or single bytes (binary strings)
        chars = n
        if op == 88 or op == 0x8C or op == 0x8D:
            for i in range(p, p + n):
                chars -= int(0x80 <= data[i] < 0xC0)
        return chars, ascii_
    chars = 0
    i = p
    while i < p + n:
        run = 0
        while i < p + n and data[i] == 92:
            run += 1
            i += 1
        if run % 2 == 1 and i < p + n and (data[i] == 117 or data[i] == 85):
            chars += run  # run - 1 backslashes, then one escaped character
            i += 5 if data[i] == 117 else 9
        else:
            chars += run + int(i < p + n)
            i += 1
    return chars, ascii_ and not slash


@njit(cache=True, nogil=True)
def _shape(nodes, ch, s):
    """(status, ndim, element count) of a shape node: status 0 ok, 1 not a tuple of at most 64 items, 2 a bad
    size. The count saturates (a mismatch, then)."""
    if nodes[s, W] & KIND_MASK != K_TUPLE or nodes[s, B] > _MAX_DIMS:
        return 1, 0, 0
    count = 1
    for i in range(nodes[s, B]):
        d = ch[nodes[s, A] + i]
        v = nodes[d, V]
        if nodes[d, W] & (KIND_MASK | F_BOOL) != K_INT or v < 0:
            return 2, 0, 0
        count = 0 if v == 0 or count == 0 else (_SAT if count > _SAT // v else count * v)
    return 0, nodes[s, B], count


@njit(cache=True, nogil=True, inline="always")
def _made(nodes, dt, count):
    """Bytes charged for an array of ``count`` elements of dtype node ``dt``: numbers at 8 bytes an element at
    least (a reader converts them to float64), str and bytes at their itemsize."""
    size = nodes[dt, V]
    kind = nodes[dt, A]
    if kind == 98 or kind == 105 or kind == 117 or kind == 102:  # b, i, u, f
        size = max(size, 8)
    return count * size


@njit(cache=True, nogil=True)
def _char(data, nodes, s):
    """The character of node s if it is a one-character ASCII str, else -1."""
    if nodes[s, W] & (KIND_MASK | F_CONTENT) == K_STR | F_CONTENT and nodes[s, B] == 1:
        return int(data[nodes[s, A]])
    return -1


#: the names of the latin-1 codec that _codecs.encode may be called with (lower case, '_' as '-'), padded
_LATIN1 = np.array([list(name.ljust(10).encode()) for name in ("latin1", "latin-1", "iso-8859-1")], np.uint8)
_LATIN1_LEN = np.array([6, 7, 10], np.int64)


@njit(cache=True, nogil=True)
def _is_latin1(data, p, n):
    """data[p:p+n] names the latin-1 codec (in any case, '_' for '-')."""
    for r in range(_LATIN1.shape[0]):
        same = n == _LATIN1_LEN[r]
        for i in range(n if same else 0):
            c = int(data[p + i])
            c = c + 32 if 65 <= c <= 90 else (45 if c == 95 else c)
            same = same and c == _LATIN1[r, i]
        if same:
            return True
    return False


@njit(cache=True, nogil=True)
def _reduce(data, nodes, ch, gtab, dblob, dtab, fn, args):
    """Check a call of allowlisted function ``fn`` (FN_*) with the tuple node ``args``. Returns (error, i0, i1,
    i2, the result's W, V, A, B, array bytes the call makes)."""
    n = nodes[args, B]
    c = ch[nodes[args, A] : nodes[args, A] + n]
    if fn == FN_RECONSTRUCT:  # (numpy.ndarray, (0,), b"b")
        if n == 3 and (nodes[c[0], W] & KIND_MASK != K_GLOBAL or gtab[nodes[c[0], V], 4] != FN_NDARRAY):
            return E_SUBTYPE, c[0], 0, 0, 0, 0, 0, 0, 0
        if (
            n != 3
            or nodes[c[1], W] & KIND_MASK != K_TUPLE
            or nodes[c[1], B] != 1
            or ch[nodes[c[1], A]] != _INT0
            or nodes[c[2], W] & (KIND_MASK | F_CONTENT) != K_BYTES | F_CONTENT
            or nodes[c[2], V] != 1
            or data[nodes[c[2], A]] != 98
        ):
            return E_HEADER, 0, 0, 0, 0, 0, 0, 0, 0
        return OK, 0, 0, 0, K_SHELL, 0, 0, 0, 0
    for k in c:
        if nodes[k, W] & F_GLOBALISH:
            return E_GLOBAL_VALUE, k, 0, 0, 0, 0, 0, 0, 0
    if fn == FN_DTYPE:  # (code, align: bool, copy=True)
        if n != 3:
            return E_DTYPE_ARGS, 0, 0, 0, 0, 0, 0, 0, 0
        q, m = nodes[c[0], A], nodes[c[0], B]
        row = -1
        if nodes[c[0], W] & (KIND_MASK | F_CONTENT) == K_STR | F_CONTENT and m > 0:
            for r in range(dtab.shape[0]):
                if dtab[r, D_ITEMSIZE] >= 0 and _equals(data, q, m, dblob, dtab[r, D_OFF], dtab[r, D_LEN]):
                    row = r
                elif (
                    dtab[r, D_ITEMSIZE] < 0
                    and data[q] == dtab[r, D_KIND]
                    and (m == 1 or _decimal(data, q + 1, q + m)[0])
                ):  # U, S, or U<n>, S<n>
                    row = r
        if row < 0:
            return E_DTYPE_CODE, c[0], 0, 0, 0, 0, 0, 0, 0
        if nodes[c[1], W] & F_BOOL == 0 or c[2] != _TRUE:
            return E_DTYPE_ARGS, 0, 0, 0, 0, 0, 0, 0, 0
        return OK, 0, 0, 0, K_DTYPE, dtab[row, D_ITEMSIZE], dtab[row, D_KIND], row, 0
    if fn == FN_ENCODE:  # (str, "latin1")
        if (
            n != 2
            or nodes[c[0], W] & KIND_MASK != K_STR
            or nodes[c[1], W] & (KIND_MASK | F_CONTENT) != K_STR | F_CONTENT
            or not _is_latin1(data, nodes[c[1], A], nodes[c[1], B])
        ):
            return E_ENCODE, 0, 0, 0, 0, 0, 0, 0, 0
        s = c[0]
        return OK, 0, 0, 0, K_BYTES | (nodes[s, W] & F_CONTENT), nodes[s, V], nodes[s, A], nodes[s, B], nodes[s, B]
    if fn == FN_ODICT or fn == FN_BYTES:  # ()
        if n:
            return (E_ODICT_ARGS if fn == FN_ODICT else E_BYTES_ARGS), 0, 0, 0, 0, 0, 0, 0, 0
        if fn == FN_ODICT:
            return OK, 0, 0, 0, K_ODICT | 1 << DEPTH_SHIFT, 0, 0, 0, 0
        return OK, 0, 0, 0, K_BYTES | F_CONTENT, 0, 0, 0, 0
    # scalar(dtype, data) and _frombuffer(data, dtype, shape, order[, axis order])
    if (fn == FN_SCALAR and n != 2) or (fn == FN_FROMBUFFER and not 4 <= n <= 5):
        return E_ARGS, 0, 0, 0, 0, 0, 0, 0, 0
    dt = c[0] if fn == FN_SCALAR else c[1]
    raw = c[1] if fn == FN_SCALAR else c[0]
    if nodes[dt, W] & KIND_MASK != K_DTYPE:
        return E_NOT_DTYPE, dt, 0, 0, 0, 0, 0, 0, 0
    if nodes[dt, W] & F_BUILT == 0:
        return E_INCOMPLETE, 0, 0, 0, 0, 0, 0, 0, 0
    if nodes[dt, A] == 79:  # 'O'
        return (E_SCALAR_OBJ if fn == FN_SCALAR else E_FROMBUF_OBJ), 0, 0, 0, 0, 0, 0, 0, 0
    rk = nodes[raw, W] & KIND_MASK
    size = nodes[raw, V]
    if fn == FN_SCALAR:
        if not (rk == K_BYTES or rk == K_STR) or size != nodes[dt, V]:
            return E_SCALAR, 0, 0, 0, 0, 0, 0, 0, 0
        return OK, 0, 0, 0, K_SCALAR, 0, 0, 0, 0
    status, nd, count = _shape(nodes, ch, c[2])
    if status:
        return E_SHAPE, 0, 0, 0, 0, 0, 0, 0, 0
    if not (rk == K_BYTES or rk == K_BYTEARRAY) or size < 0:
        return E_RAWTYPE, 0, 0, 0, 0, 0, 0, 0, 0
    if n == 4:
        order_ok = _char(data, nodes, c[3]) == 67 or _char(data, nodes, c[3]) == 70  # C, F
    else:  # K, with the axis order: a permutation of range(ndim)
        order_ok = _char(data, nodes, c[3]) == 75 and nodes[c[4], W] & KIND_MASK == K_TUPLE and nodes[c[4], B] == nd
        seen = 0
        for k in ch[nodes[c[4], A] : nodes[c[4], A] + (nd if order_ok else 0)]:
            v = nodes[k, V]
            order_ok = order_ok and nodes[k, W] & (KIND_MASK | F_BOOL) == K_INT and 0 <= v < nd and not seen >> v & 1
            seen |= 1 << min(max(v, 0), 62)
    if not order_ok:
        return E_ORDER, 0, 0, 0, 0, 0, 0, 0, 0
    if count >= _SAT // 64 or count * nodes[dt, V] != size:
        return E_SIZE, c[2], dt, size, 0, 0, 0, 0, 0
    return OK, 0, 0, 0, K_ARRAY, 0, 0, 0, _made(nodes, dt, count)


@njit(cache=True, nogil=True)
def _build(data, nodes, ch, dtab, target, state):
    """Check BUILD of ``state`` on ``target``. Returns (error, i0, i1, i2, itemsize of a dtype, array bytes)."""
    tk = nodes[target, W] & KIND_MASK
    if nodes[target, W] & (F_BUILT | F_PLACED) or not (tk == K_SHELL or tk == K_DTYPE):
        return E_BUILD, target, 0, 0, 0, 0
    sk = nodes[state, W] & KIND_MASK
    n = nodes[state, B] if sk == K_TUPLE else 0
    c = ch[nodes[state, A] : nodes[state, A] + n]
    if tk == K_DTYPE:
        row = nodes[target, B]
        if n != 8 or c[0] != _INT0 + 3 or c[2] != _NONE or c[3] != _NONE or c[4] != _NONE:
            return E_DTYPE_STATE, 0, 0, 0, 0, 0
        bo = _char(data, nodes, c[1])
        bit = int(bo == 60) | 2 * int(bo == 62) | 4 * int(bo == 124)  # '<', '>', '|'
        ints_ok = True
        for k in c[5:]:
            ints_ok = ints_ok and nodes[k, W] & (KIND_MASK | F_BOOL) == K_INT
        elsize, align, flags = nodes[c[5], V], nodes[c[6], V], nodes[c[7], V]
        if not ints_ok or not dtab[row, D_BO] & bit or align != dtab[row, D_ALIGN] or flags != dtab[row, D_FLAGS]:
            return E_DTYPE_STATE, 0, 0, 0, 0, 0
        if dtab[row, D_ITEMSIZE] >= 0:
            return (E_DTYPE_STATE if elsize != dtab[row, D_ELSIZE] else OK), 0, 0, 0, dtab[row, D_ITEMSIZE], 0
        if elsize < 0 or elsize >= 1 << 40 or (dtab[row, D_KIND] == 85 and elsize % 4):
            return E_DTYPE_SIZE, 0, elsize, 0, 0, 0
        return OK, 0, 0, 0, elsize, 0
    if n != 5 or c[0] != _INT0 + 1:
        return E_ARRSTATE, 0, 0, 0, 0, 0
    status, nd, count = _shape(nodes, ch, c[1])
    dt, raw = c[2], c[4]
    if status:
        return E_SHAPE, 0, 0, 0, 0, 0
    if nodes[dt, W] & KIND_MASK != K_DTYPE:
        return E_NOT_DTYPE, dt, 0, 0, 0, 0
    if nodes[dt, W] & F_BUILT == 0:
        return E_INCOMPLETE, 0, 0, 0, 0, 0
    if nodes[c[3], W] & F_BOOL == 0:
        return E_ORDER, 0, 0, 0, 0, 0
    rk = nodes[raw, W] & KIND_MASK
    if nodes[dt, A] == 79:  # object dtype: a list of plain items
        if rk != K_LIST:
            return E_RAWTYPE, 0, 0, 0, 0, 0
        if nodes[raw, V] != count:
            return E_LIST, 0, c[1], 0, 0, 0
        if nodes[raw, W] & F_LEAVES == 0:
            return E_OBJ_ITEMS, 0, 0, 0, 0, 0
        return OK, 0, 0, 0, 0, 8 * count
    size = nodes[raw, V]
    if not (rk == K_BYTES or rk == K_STR) or size < 0:
        return E_RAWTYPE, 0, 0, 0, 0, 0
    if count >= _SAT // 64 or count * nodes[dt, V] != size:
        return E_SIZE, c[1], dt, size, 0, 0
    return OK, 0, 0, 0, 0, _made(nodes, dt, count)


@njit(cache=True, nogil=True, inline="always")
def _hash_cost(nodes, k):
    """Tuple elements hashed when node k is a dict key or set member (0 for the other hashable kinds: their
    hash is cheap, or cached for str); -1 if it cannot be hashed."""
    w = nodes[k, W]
    if not (1 << (w & KIND_MASK)) & _HASHABLE or w & F_UNHASHABLE:
        return -1
    return nodes[k, V] if w & KIND_MASK == K_TUPLE else 0


@njit(cache=True, nogil=True)
def scan(data, gblob, gtab, dblob, dtab, budget, max_depth, key_budget, nodes, ch, stack, marks, memo, items):
    """Check the pickle in ``data`` (read-only uint8).

    ``gblob``/``gtab``: the allowlist (rows: module offset, length, name offset, length, FN_*);
    ``dblob``/``dtab``: the accepted dtype codes (columns D_*). ``nodes`` (N, 4; the first rows
    :data:`BASE_NODES`), ``ch``, ``stack``, ``marks``, ``memo`` (zeros; it keeps node + 1 per filled
    slot) and ``items`` (M, 3), all int64, are room to work in; when one is too small the scan returns E_ROOM
    naming it (i0) and the size it needs (i1), to be called again. ``items`` is also a record: every item put
    into a list, dict or OrderedDict, in order, as rows (container, item, -1) or (dict, key, value); with the
    state node of each built array (a K_SHELL's A) it is what :mod:`kitti_eval.io.pickle_columns` reads. The
    record decides nothing: the checks are the same with or without it.

    Returns ``(code, pos, i0, i1, i2, nodes used, children used, result, items used)``: OK or an E_* code for
    the opcode at byte ``pos`` with details i0..i2; how many nodes and tuple children there are (for messages),
    the node STOP returns, and how many rows of ``items`` are filled.
    """
    n = data.shape[0]
    nn, nch, sp, nmarks, fence = _FIRST, 0, 0, 0, 0
    memo_len, writes, spent, again, hashed, ni = 0, 0, 0, 0, 0, 0
    strings, widest = 0, 0  # elements of str ('U') arrays, and the largest itemsize among them
    pos, p0, err, i0, i1, i2, result = 0, 0, OK, 0, 0, 0, -1
    while True:
        if pos >= n:
            err = E_TRUNC
            break
        p0 = pos
        op = int(data[pos])
        pos += 1
        if nn + 1 >= nodes.shape[0]:
            err, i0, i1 = E_ROOM, ROOM_NODES, 2 * nn
            break
        if sp + 1 >= stack.shape[0]:
            err, i0, i1 = E_ROOM, ROOM_STACK, 2 * sp
            break
        # ------------------------------------------------------------ arguments, framed as _pickle.c does
        err = _REFUSED[op]
        fixed, width = _FIXED[op], _COUNTED[op]
        if err or pos + fixed + width > n:
            err = err if err else E_TRUNC
            break
        size = -1
        if width:
            size = _uint(data, pos, width)
            pos += width
            if size < 0 or (op == 0x54 and size >= 1 << 31):  # BINSTRING's length is signed
                err = E_BADARG
                break
            if size > n - pos:
                err = E_TRUNC
                break
        line = pos
        if _LINES[op]:
            line = _line_end(data, pos)
            if line < 0:
                err = E_TRUNC
                break
        push = -1  # a node to push: an existing one, or nn for a new one with w, v, a, b, x, strs
        w, v, a, b, x, strs = _NEW[op], 0, nch, 0, 0, 0
        # ------------------------------------------------------------ values
        if width or op == 0x53 or op == 0x56:  # counted str/bytes/bytearray; STRING (quoted); UNICODE
            a, b = pos, size
            if not width:
                a, b = pos, line - pos
                if op == 0x53:
                    if b < 2 or data[a] != data[line - 1] or not (data[a] == 39 or data[a] == 34):
                        err = E_BADARG
                        break
                    a, b = a + 1, b - 2
            v = b
            if w == K_STR:
                v, content = _text(data, a, b, op)
                if content:
                    w |= F_CONTENT
            pos = line + 1 if not width else pos + size
            push = nn
        elif op == 0x4E:  # NONE
            push = _NONE
        elif op == 0x88:  # NEWTRUE
            push = _TRUE
        elif op == 0x89:  # NEWFALSE
            push = _FALSE
        elif op == 0x4B or op == 0x4D or op == 0x4A:  # BININT1, BININT2, BININT
            v = _uint(data, pos, fixed)
            if fixed == 4 and v >= 1 << 31:
                v -= 1 << 32
            w = K_INT
            push = nn
            pos += fixed
        elif op == 0x8A or op == 0x8B:  # LONG1, LONG4: two's complement, little-endian
            size = _uint(data, pos, fixed)
            pos += fixed
            if size >= 1 << 31:
                err = E_BADARG
                break
            if size > n - pos:
                err = E_TRUNC
                break
            push = _BIGINT
            if size <= 8:
                for i in range(min(size, 7)):
                    v |= int(data[pos + i]) << (8 * i)
                if size == 8:
                    v += (int(data[pos + 7]) - 256 * int(data[pos + 7] >= 128)) * (1 << 56)
                elif size and data[pos + size - 1] >= 128:
                    v -= 1 << (8 * size)
                w = K_INT
                push = nn
            pos += size
        elif op == 0x49:  # INT (I00 and I01 are bools)
            ok, v = _decimal(data, pos, line)
            w = K_INT
            push = nn if ok else _BIGINT
            if line - pos == 2 and data[pos] == 48 and (data[pos + 1] == 48 or data[pos + 1] == 49):
                push = _TRUE if data[pos + 1] == 49 else _FALSE
            pos = line + 1
        elif op == 0x4C:  # LONG
            push = _BIGINT
            pos = line + 1
        elif op == 0x46 or op == 0x47:  # FLOAT, BINFLOAT
            push = _FLOAT
            pos = line + 1 if op == 0x46 else pos + 8
        elif op == 0x29 or op == 0x5D or op == 0x7D or op == 0x8F:  # EMPTY_TUPLE, _LIST, _DICT, _SET
            w |= 1 << DEPTH_SHIFT
            push = nn
        # ------------------------------------------------------------ the stack and the memo
        elif op == 0x28:  # MARK
            if nmarks == marks.shape[0]:
                err, i0, i1 = E_ROOM, ROOM_MARKS, 2 * nmarks
                break
            marks[nmarks] = sp
            nmarks += 1
            fence = sp
        elif op == 0x30:  # POP (of a MARK, if one is on top)
            if nmarks and marks[nmarks - 1] == sp:
                nmarks -= 1
                fence = marks[nmarks - 1] if nmarks else 0
            elif sp <= fence:
                err = E_UNDERFLOW
                break
            else:
                sp -= 1
        elif op == 0x31:  # POP_MARK
            if not nmarks:
                err = E_NOMARK
                break
            nmarks -= 1
            sp = marks[nmarks]
            fence = marks[nmarks - 1] if nmarks else 0
        elif op == 0x32:  # DUP
            if sp <= fence:
                err = E_UNDERFLOW
                break
            push = stack[sp - 1]
        elif op == 0x67 or op == 0x68 or op == 0x6A:  # GET, BINGET, LONG_BINGET
            idx, pos = _memo_index(data, pos, fixed, line)
            if idx < 0 or idx >= memo.shape[0] or memo[idx] == 0:
                err, i0 = (E_BADARG if idx < 0 else E_MEMO), idx
                break
            push = memo[idx] - 1
        elif op == 0x70 or op == 0x71 or op == 0x72 or op == 0x94:  # PUT, BINPUT, LONG_BINPUT, MEMOIZE
            idx = memo_len
            if op != 0x94:
                idx, pos = _memo_index(data, pos, fixed, line)
            if idx < 0 or sp <= fence:
                err = E_BADARG if idx < 0 else E_UNDERFLOW
                break
            if idx > writes + 1024:
                err, i0 = E_MEMO_RANGE, idx
                break
            if idx >= memo.shape[0]:
                err, i0, i1 = E_ROOM, ROOM_MEMO, max(2 * memo.shape[0], idx + 1)
                break
            memo_len += int(memo[idx] == 0)
            memo[idx] = stack[sp - 1] + 1
            writes += 1
        elif op == 0x80:  # PROTO
            if data[pos] > 5:
                err = E_BADARG
                break
            pos += 1
        elif op == 0x95:  # FRAME: its bytes must all be there
            size = _uint(data, pos, fixed)
            pos += fixed
            if size < 0 or size > n - pos:
                err = E_TRUNC
                break
        elif op == 0x2E:  # STOP
            if sp <= fence:
                err = E_UNDERFLOW
                break
            result = stack[sp - 1]
            if nodes[result, W] & F_GLOBALISH:
                err, i0 = E_GLOBAL_VALUE, result
            break
        # ------------------------------------------------------------ globals, calls and states
        elif op == 0x63 or op == 0x93:  # GLOBAL, STACK_GLOBAL
            known = True
            if op == 0x63:
                end = _line_end(data, line + 1)
                if end < 0:
                    err = E_TRUNC
                    break
                i1, mlen, i2, qlen = pos, line - pos, line + 1, end - line - 1
                pos = end + 1
            else:
                if sp - 2 < fence:
                    err = E_UNDERFLOW
                    break
                sp -= 2
                i1, i2 = stack[sp], stack[sp + 1]
                if nodes[i1, W] & KIND_MASK != K_STR or nodes[i2, W] & KIND_MASK != K_STR:
                    err = E_BADARG
                    break
                known = nodes[i1, W] & nodes[i2, W] & F_CONTENT != 0
                mlen, qlen = nodes[i1, B], nodes[i2, B]
                i1, i2 = nodes[i1, A], nodes[i2, A]
            row = -1
            for g in range(gtab.shape[0]):
                if (
                    known
                    and _equals(data, i1, mlen, gblob, gtab[g, 0], gtab[g, 1])
                    and _equals(data, i2, qlen, gblob, gtab[g, 2], gtab[g, 3])
                ):
                    row = g
            if row < 0:
                err, i0 = E_GLOBAL, int(op == 0x93)
                if op == 0x93:
                    i1, i2 = stack[sp], stack[sp + 1]
                break
            w, v, push = K_GLOBAL | F_GLOBALISH, row, nn
        elif op == 0x52:  # REDUCE
            if sp - 2 < fence:
                err = E_UNDERFLOW
                break
            sp -= 2
            call, args = stack[sp], stack[sp + 1]
            if nodes[call, W] & KIND_MASK != K_GLOBAL or gtab[nodes[call, V], 4] == FN_NDARRAY:
                err, i0 = E_CALL, call
                break
            if nodes[args, W] & KIND_MASK != K_TUPLE:
                err = E_NOT_TUPLE
                break
            err, i0, i1, i2, w, v, a, b, made = _reduce(
                data, nodes, ch, gtab, dblob, dtab, gtab[nodes[call, V], 4], args
            )
            spent += made
            if w & KIND_MASK == K_ARRAY:
                x = made
                dt = ch[nodes[args, A] + 1]
                if not err and nodes[dt, A] == 85 and nodes[dt, V] > 0:  # a str array
                    strs = made // nodes[dt, V]
                    strings += strs
                    widest = max(widest, nodes[dt, V])
                    if strings > budget // widest:
                        err, i0, i1 = E_WIDE, strings, widest
            if w & KIND_MASK == K_SCALAR:
                a = args  # its (dtype, bytes), for the columns
            push = nn
        elif op == 0x62:  # BUILD
            if sp - 2 < fence:
                err = E_UNDERFLOW
                break
            sp -= 1
            target = stack[sp - 1]
            err, i0, i1, i2, itemsize, made = _build(data, nodes, ch, dtab, target, stack[sp])
            nodes[target, W] |= F_BUILT
            if nodes[target, W] & KIND_MASK == K_DTYPE:
                nodes[target, V] = itemsize
                if not err and _char(data, nodes, ch[nodes[stack[sp], A] + 1]) == 62:  # '>'
                    nodes[target, W] |= F_BIG
            elif not err:
                nodes[target, A] = stack[sp]  # the state, for the columns (kitti_eval.io.pickle_columns)
                nodes[target, X] = made
                dt = ch[nodes[stack[sp], A] + 2]
                if nodes[dt, A] == 85 and nodes[dt, V] > 0:  # a str array
                    nodes[target, S] = made // nodes[dt, V]
                    strings += nodes[target, S]
                    widest = max(widest, nodes[dt, V])
                    if strings > budget // widest:
                        err, i0, i1 = E_WIDE, strings, widest
            spent += made
        # ------------------------------------------------------------ containers
        elif w or _INTO[op]:  # TUPLE, TUPLE1-3, LIST, DICT, FROZENSET; APPEND(S), SETITEM(S), ADDITEMS
            first = sp - 1 if op == 0x61 else sp - 2
            if op >= 0x85 and op <= 0x87:
                first = sp - (op - 0x84)
            if _FROM_MARK[op]:
                if not nmarks:
                    err = E_NOMARK
                    break
                nmarks -= 1
                first = marks[nmarks]
                fence = marks[nmarks - 1] if nmarks else 0
            if first < fence:
                err = E_UNDERFLOW
                break
            target = -1
            if not _INTO[op]:
                w |= 1 << DEPTH_SHIFT
            else:
                if first - 1 < fence:
                    err = E_UNDERFLOW
                    break
                target = stack[first - 1]
                tk = nodes[target, W] & KIND_MASK
                if tk != _INTO[op] and not (tk == K_ODICT and _INTO[op] == K_DICT):
                    err, i0 = E_TARGET, target
                    break
                if nodes[target, W] & F_PLACED:
                    err = E_CHANGED
                    break
                w, v, x, strs = nodes[target, W], nodes[target, V], nodes[target, X], nodes[target, S]
            keyed = op == 0x64 or op == 0x73 or op == 0x75
            if keyed and (sp - first) % 2:
                err = E_ODD
                break
            is_tuple = w & KIND_MASK == K_TUPLE
            logged = w & KIND_MASK == K_LIST or w & KIND_MASK == K_DICT or w & KIND_MASK == K_ODICT
            if logged and ni + sp - first >= items.shape[0]:
                err, i0, i1 = E_ROOM, ROOM_ITEMS, 2 * (ni + sp - first)
                break
            if is_tuple:
                if nch + sp - first >= ch.shape[0]:
                    err, i0, i1 = E_ROOM, ROOM_CH, 2 * (nch + sp - first)
                    break
                v = sp - first
            for j in range(first, sp):
                k = stack[j]
                kw = nodes[k, W]
                if kw & F_GLOBALISH and not is_tuple:
                    err, i0 = E_GLOBAL_VALUE, k
                    break
                if k == target:
                    err = E_CHANGED
                    break
                if op == 0x91 or op == 0x90 or (keyed and (j - first) % 2 == 0):
                    cost = _hash_cost(nodes, k)
                    if cost < 0:
                        err, i0 = E_UNHASHABLE, k
                        break
                    hashed += cost
                    if hashed > key_budget:
                        err = E_KEYS
                        break
                depth = ((kw >> DEPTH_SHIFT) & 0xFFFF) + 1
                if depth > max_depth:
                    err = E_DEPTH
                    break
                if depth > (w >> DEPTH_SHIFT) & 0xFFFF:
                    w = (w & ~(0xFFFF << DEPTH_SHIFT)) | depth << DEPTH_SHIFT
                if is_tuple:
                    ch[nch] = k
                    nch += 1
                    w |= kw & F_GLOBALISH
                    if _hash_cost(nodes, k) < 0:
                        w |= F_UNHASHABLE
                    if kw & KIND_MASK == K_TUPLE:
                        v = min(v + nodes[k, V], _SAT)
                elif w & KIND_MASK == K_LIST:
                    v += 1
                    if not (1 << (kw & KIND_MASK)) & _LEAVES:
                        w &= ~F_LEAVES
                held = nodes[k, X]
                if kw & F_PLACED:  # in a container already: a reader copies its arrays again, once a place
                    spent = min(spent + held, _SAT)
                    again = min(again + held, _SAT)
                    strings = min(strings + nodes[k, S], _SAT)
                    if widest and strings > budget // widest:
                        err, i0, i1 = E_WIDE, strings, widest
                        break
                x = min(x + held, _SAT)
                strs = min(strs + nodes[k, S], _SAT)
                if k >= _FIRST:
                    nodes[k, W] |= F_PLACED
            b = sp - first
            spent += _ITEM_BYTES * b
            if logged and not err:  # the items, in order: (container, item, -1) or (dict, key, value)
                step = 2 if keyed else 1
                for j in range(first, sp, step):
                    items[ni, 0] = target if target >= 0 else nn
                    items[ni, 1] = stack[j]
                    items[ni, 2] = stack[j + 1] if keyed else -1
                    ni += 1
            sp = first
            if target >= 0:
                nodes[target, W], nodes[target, V], nodes[target, X], nodes[target, S] = w, v, x, strs
            else:
                push = nn
        else:
            err, i0 = E_OPCODE, op
        if err:
            break
        if spent + 8 * sp > budget:
            err, i0, i1 = E_BUDGET, min(spent + 8 * sp, _SAT), again
            break
        if push == nn:
            if w & KIND_MASK == K_INT and 0 <= v < 256:
                push = _INT0 + v
            else:
                nodes[nn, W], nodes[nn, V], nodes[nn, A], nodes[nn, B] = w | op << OP_SHIFT, v, a, b
                nodes[nn, X], nodes[nn, S] = x, strs
                nn += 1
                spent += _OBJECT_BYTES
        if push >= 0:
            stack[sp] = push
            sp += 1
    return err, p0, i0, i1, i2, nn, nch, result, ni
