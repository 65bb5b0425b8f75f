"""The checking half of :func:`kitti_eval.safe_pickle.load_pickle`: a pickle VM over types, run ahead of loading.

:func:`scan` walks the opcode stream of a pickle (protocols 0-5) at native speed and models what CPython's
C unpickler (``_pickle.c``) would do with it, value by value: the stack, the MARK stack (with its fence),
the memo, and for every object a node that records its kind and whatever the checks need (the value of
an int, the length and the position of a str or bytes, the children of a tuple, the length of a list, the
dtype of an array, the nesting depth of a container, which global a REDUCE calls). It accepts a pickle
only if every call, every BUILD and every container operation the C unpickler would perform is one of
the allowed ones with checked arguments; :func:`~kitti_eval.safe_pickle.load_pickle` lets the C
unpickler build the objects from the checked bytes only, with ``find_class`` returning the real numpy
reconstructors (and checking that each global it is asked for is the one the scan saw at that point of
the stream).

What the scan enforces (beyond parsing every opcode exactly as ``_pickle.c`` does, or more strictly):

* globals only from the allowlist; a global is only ever called (REDUCE) or passed as the subtype of
  ``_reconstruct``; it never becomes a value (in a container or as the result);
* REDUCE on an allowlisted callable with the arguments numpy itself writes: ``_reconstruct(ndarray,
  shape of size 0, b"b")``; ``dtype(code, align, True)`` for a plain numeric, str, bytes or object code;
  ``scalar(complete plain dtype, bytes of its itemsize)``; ``_frombuffer(bytes, complete non-object
  dtype, shape, order[, axis order])`` with exactly ``prod(shape) * itemsize`` bytes;
  ``_codecs.encode(str, latin-1)``; ``OrderedDict()`` and ``bytes()`` without arguments;
* BUILD only once, and only on a fresh array shell (state: a complete plain dtype, a shape, and exactly
  ``prod(shape) * itemsize`` bytes, or for object arrays a list of exactly ``prod(shape)`` str, numbers,
  bytes, None or numpy scalars) or a fresh dtype (state: exactly the canonical state of a plain dtype);
* APPEND(S) only on lists, SETITEM(S) only on dicts and OrderedDicts, ADDITEMS only on sets; a container
  cannot be changed once it has been put into another one (so there are no cycles and the depth of every
  container is known when it is built); dict keys and set members must be hashable;
* containers nest at most ``max_depth`` deep (CPython's tuple hash recurses in C without a guard), the
  tuples hashed as dict keys and set members hold at most ``key_budget`` tuple elements in all (a tuple
  DAG of depth 100 that repeats each child would otherwise hash for ever);
* the array bytes that calls and BUILDs produce are budgeted (a small pickle cannot claim a huge array);
* memo indices stay below the number of memo writes + 1024 (the C unpickler allocates the memo as an
  array up to twice the largest index);
* no NEWOBJ, NEWOBJ_EX, INST, OBJ, EXT1/2/4, PERSID, BINPERSID, NEXT_BUFFER, READONLY_BUFFER.

While it runs, the scan publishes how many bytes it has accepted (``progress[0]``, an atomic store with
release order): :mod:`kitti_eval.safe_pickle` feeds the C unpickler only those bytes, so the two can run
side by side (the scan releases the GIL) without the C unpickler ever parsing an opcode that was not
checked. The scan writes the globals (rows of the allowlist) in stream order into ``gseq`` before it
publishes the bytes that name them; on failure it returns an error code, the byte offset of the opcode
and up to three details (node ids or offsets) from which :mod:`kitti_eval.safe_pickle` writes the message.

The model follows CPython 3.11's ``Modules/_pickle.c`` (``load_*``): the stack and its MARK fence,
``POP`` taking a MARK at the top, ``MEMOIZE`` writing at the number of filled memo slots, ``INT``'s
``I00``/``I01`` being bools, ``FRAME`` needing its bytes present. Where ``_pickle.c`` is lenient (e.g. a
no-op ``APPENDS`` on any object, digits with spaces in ``GET``) the scan is stricter; it never accepts
what the C unpickler would do differently.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numba.core import cgutils, types
from numba.core.extending import intrinsic

# ------------------------------------------------------------------------------------------ error codes
OK = 0
# not a readable pickle (InputError)
E_TRUNC = 1          # the data ends inside an opcode or before STOP
E_OPCODE = 2         # unknown opcode
E_UNDERFLOW = 3      # stack underflow (or an object taken across a MARK)
E_NOMARK = 4         # an opcode needs a MARK that is not there
E_BADARG = 5         # a malformed opcode argument (PROTO > 5, unquoted STRING, bad GET/PUT line, ...)
E_MEMO = 6           # GET of an index that holds nothing
E_MEMO_RANGE = 7     # memo index far beyond the number of memo writes
E_ODD = 8            # odd number of items for DICT / SETITEMS
E_DEPTH = 9          # containers nested more than max_depth deep
E_KEYS = 10          # tuple keys hold more than key_budget elements in all
E_UNHASHABLE = 11    # dict key or set item that cannot be hashed
E_CHANGED = 12       # a container changed after it was put into another one
E_BUDGET = 13        # more array bytes built than the budget allows
E_OOB = 14           # out-of-band buffers (NEXT_BUFFER, READONLY_BUFFER)
E_NOT_TUPLE = 15     # REDUCE arguments that are not a tuple
E_HEADER = 16        # _reconstruct arguments other than numpy's empty int8 shell
E_SHAPE = 17         # a shape that is not a tuple of at most 64 sizes >= 0
E_SIZE = 18          # array/buffer bytes differ from prod(shape) * itemsize
E_LIST = 19          # object array state list of the wrong length
E_ARRSTATE = 20      # array state that is not (1, shape, dtype, fortran, data)
E_INCOMPLETE = 21    # a dtype used before its state was set
E_RAWTYPE = 22       # array data of the wrong type (or of a size the scan cannot know)
E_ORDER = 23         # bad order / axis order / fortran flag
E_SCALAR = 24        # numpy scalar data of the wrong size or type
E_FROMBUF_OBJ = 25   # object dtype from a raw buffer
E_DTYPE_SIZE = 26    # bad str/bytes size in a dtype state
E_ARGS = 27          # wrong number or kind of call arguments
E_GLOBALS = 28       # more globals than the room the caller gave
E_CANCELLED = 29     # the caller set progress[1] (it stopped loading)
# refused (UnsafePickleError)
E_GLOBAL = 40        # a global outside the allowlist (i0: 0 GLOBAL / 1 STACK_GLOBAL, i1, i2: see safe_pickle)
E_NEWOBJ = 41
E_INST = 42
E_EXT = 43
E_PERSID = 44
E_CALL = 45          # REDUCE on something that is not an allowlisted callable (i0: node)
E_BUILD = 46         # BUILD on something other than a fresh array shell or dtype (i0: node)
E_GLOBAL_VALUE = 47  # a global used as a value (i0: node)
E_DTYPE_CODE = 48    # numpy.dtype code not accepted (i0: node of the code)
E_DTYPE_STATE = 49   # dtype state other than the canonical plain state (i0: dtype node)
E_SUBTYPE = 50       # _reconstruct of something other than numpy.ndarray (i0: node)
E_OBJ_ITEMS = 51     # object array holding something other than str, numbers, bytes, None
E_ENCODE = 52        # _codecs.encode other than str -> latin-1
E_ODICT_ARGS = 53
E_BYTES_ARGS = 54
E_SCALAR_OBJ = 55    # numpy scalar of object dtype
E_NOT_DTYPE = 56     # something other than a dtype where numpy expects one
E_TARGET = 57        # APPENDS / SETITEMS / ADDITEMS on an object of the wrong kind (i0: node)
E_DTYPE_ARGS = 58    # numpy.dtype called other than (code, align: bool, copy=True)

# ------------------------------------------------------------------------------------------ node kinds
K_NONE = 1
K_INT = 2          # an int (or bool) whose value fits in int64: V
K_BIGINT = 3       # an int (or bool) whose value the scan does not know
K_FLOAT = 4
K_STR = 5          # V chars (if F_EXACT); raw bytes data[A:A+B] (comparable to ASCII text if F_CONTENT)
K_BYTES = 6        # V bytes (if F_EXACT), at most B; content data[A:A+V] if F_CONTENT
K_BYTEARRAY = 7    # V bytes at data[A:]
K_TUPLE = 8        # children ch[A:A+B]; V: elements hashed when it is a key (len + that of tuple children)
K_LIST = 9         # V items
K_DICT = 10
K_SET = 11
K_FROZENSET = 12
K_ODICT = 13
K_GLOBAL = 14      # V: row of the allowlist
K_SHELL = 15       # numpy array from _reconstruct; F_BUILT once its state is set
K_ARRAY = 16       # numpy array from _frombuffer (complete)
K_DTYPE = 17       # V itemsize, A kind letter, B dtype-table row; F_BUILT once its state is set
K_SCALAR = 18      # numpy scalar (not object)

KIND_NAMES = {K_NONE: "None", K_INT: "int", K_BIGINT: "int", K_FLOAT: "float", K_STR: "str",
              K_BYTES: "bytes", K_BYTEARRAY: "bytearray", K_TUPLE: "tuple", K_LIST: "list", K_DICT: "dict",
              K_SET: "set", K_FROZENSET: "frozenset", K_ODICT: "OrderedDict", K_GLOBAL: "global",
              K_SHELL: "numpy array", K_ARRAY: "numpy array", K_DTYPE: "numpy dtype",
              K_SCALAR: "numpy scalar"}

# a node is one row of 4 int64: W = kind | flags | opcode << 24 | depth << 32, then V, A, B (per kind, above)
W = 0
V = 1
A = 2
B = 3
N_COLS = 4
KIND_MASK = 0xFF
OP_SHIFT = 24
DEPTH_SHIFT = 32
DEPTH_MASK = 0xFFFF << DEPTH_SHIFT

# flags (in W)
F_PLACED = 1 << 8       # mutable container that is inside another container (frozen from then on)
F_GLOBALISH = 1 << 9    # a global, or a tuple holding one
F_BUILT = 1 << 10
F_BOOL = 1 << 11
F_EXACT = 1 << 12
F_CONTENT = 1 << 13
F_ASCII = 1 << 14
F_ALLLEAF = 1 << 15     # list: every item may go into an object array
F_UNHASHABLE = 1 << 16  # tuple: holds something unhashable

# allowlisted callables (column 4 of the globals table)
FN_RECONSTRUCT = 1
FN_FROMBUFFER = 2
FN_NDARRAY = 3
FN_DTYPE = 4
FN_SCALAR = 5
FN_ENCODE = 6
FN_ODICT = 7
FN_BYTES = 8

_LEAF_KINDS = ((1 << K_NONE) | (1 << K_INT) | (1 << K_BIGINT) | (1 << K_FLOAT) | (1 << K_STR)
               | (1 << K_BYTES) | (1 << K_SCALAR))
_HASHABLE_KINDS = _LEAF_KINDS | (1 << K_TUPLE) | (1 << K_FROZENSET) | (1 << K_DTYPE) | (1 << K_GLOBAL)
_MUTABLE_KINDS = (1 << K_LIST) | (1 << K_DICT) | (1 << K_SET) | (1 << K_ODICT)
_CONTAINER_KINDS = _MUTABLE_KINDS | (1 << K_TUPLE) | (1 << K_FROZENSET)
_SMALL_INTS = 3  # node 0 is None, 1 True, 2 False, 3 + i the int i for 0 <= i < 256
_FIRST_NODE = _SMALL_INTS + 256
_SAT = 1 << 62
_TSIZE_SAT = 1 << 40
_MAX_DIMS = 64

# dtype table columns (rows built by safe_pickle from numpy itself)
D_OFF = 0       # code in dblob
D_LEN = 1
D_KIND = 2      # kind letter
D_ITEMSIZE = 3  # -1 for U and S (the state gives it)
D_BO = 4        # allowed byteorder letters, bit 0 '<', bit 1 '>', bit 2 '|'
D_ELSIZE = 5    # canonical state fields 5..7 (elsize -1 for fixed-size kinds)
D_ALIGN = 6
D_FLAGS = 7

# the scan's state between rounds of _run (a round ends when an array needs more room)
S_POS = 0
S_NN = 1
S_NCH = 2
S_SP = 3
S_NMARKS = 4
S_FENCE = 5
S_MEMO_LEN = 6
S_MEMO_WRITES = 7
S_NGSEQ = 8
S_BUDGET = 9
S_KEYS = 10
S_ERR = 11
S_I0 = 12
S_I1 = 13
S_I2 = 14
S_RESULT = 15
S_NEED = 16
S_MEMO_INIT = 17   # memo[:S_MEMO_INIT] is initialised (-1: empty); the rest is not
N_STATE = 18

_DONE = 0
_NEED_NODES = 1
_NEED_STACK = 2
_NEED_CH = 3
_NEED_MARKS = 4
_NEED_MEMO = 5
_PUBLISH_EVERY = 1 << 14  # bytes of input between two updates of progress[0]


@intrinsic
def _store_release(typingctx, arr, idx, val):
    """arr[idx] = val as an atomic store with release order (earlier writes are visible first)."""
    sig = types.void(arr, types.intp, types.int64)

    def codegen(context, builder, signature, args):
        arrty = signature.args[0]
        ary = context.make_array(arrty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, arrty, ary, [args[1]])
        builder.store_atomic(args[2], ptr, ordering="release", align=8)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def _load_acquire(typingctx, arr, idx):
    """arr[idx] as an atomic load with acquire order (later reads see what was written before it)."""
    sig = types.int64(arr, types.intp)

    def codegen(context, builder, signature, args):
        arrty = signature.args[0]
        ary = context.make_array(arrty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, arrty, ary, [args[1]])
        return builder.load_atomic(ptr, ordering="acquire", align=8)

    return sig, codegen


@nb.njit(cache=True, nogil=True)
def validated(progress):
    """How many bytes of the input the scan has checked so far: every opcode before is allowed."""
    return _load_acquire(progress, 0)


@nb.njit(cache=True, nogil=True)
def _grow_rows(a, need):
    cap = max(a.shape[0], 16)
    while cap < need:
        cap *= 2
    b = np.empty((cap, a.shape[1]), a.dtype)
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            b[i, j] = a[i, j]
    return b


@nb.njit(cache=True, nogil=True)
def _grow(a, need, fill):
    cap = max(a.shape[0], 16)
    while cap < need:
        cap *= 2
    b = np.empty(cap, a.dtype)
    b[:a.shape[0]] = a
    b[a.shape[0]:] = fill
    return b


@nb.njit(cache=True, nogil=True)
def _line_end(data, p):
    """Index of the first newline at or after p, or -1."""
    for i in range(p, data.shape[0]):
        if data[i] == 10:
            return i
    return -1


@nb.njit(cache=True, nogil=True, inline="always")
def _uint_le(data, p, nbytes):
    x = np.int64(0)
    for i in range(nbytes):
        x |= np.int64(data[p + i]) << (8 * i)
    return x


@nb.njit(cache=True, nogil=True, inline="always")
def _size_le(data, p, nbytes):
    """calc_binsize: an unsigned little-endian size, -1 if it does not fit in 63 bits."""
    for i in range(7, nbytes):
        if data[p + i] != 0:
            return np.int64(-1)
    if nbytes >= 8 and data[p + 7] >= 128:
        return np.int64(-1)
    x = np.int64(0)
    for i in range(min(nbytes, 8)):
        x |= np.int64(data[p + i]) << (8 * i)
    return x


@nb.njit(cache=True, nogil=True)
def _decimal(data, p, e, signed):
    """Strict decimal int in data[p:e] ('-'? digits, no leading zero): (ok, value); ok is False when the
    text is anything else or has more than 18 digits (the caller then treats the value as unknown)."""
    neg = False
    if signed and p < e and data[p] == 45:
        neg = True
        p += 1
    nd = e - p
    if nd < 1 or nd > 18:
        return False, np.int64(0)
    if data[p] == 48 and (nd > 1 or neg):
        return False, np.int64(0)
    v = np.int64(0)
    for i in range(p, e):
        c = data[i]
        if c < 48 or c > 57:
            return False, np.int64(0)
        v = v * 10 + (c - 48)
    return True, -v if neg else v


@nb.njit(cache=True, nogil=True)
def _digits(data, p, e):
    """Memo index of a GET/PUT line: digits only; -1 when malformed, _SAT when absurdly large."""
    if e - p < 1:
        return np.int64(-1)
    v = np.int64(0)
    for i in range(p, e):
        c = data[i]
        if c < 48 or c > 57:
            return np.int64(-1)
        if v < _SAT // 10:
            v = v * 10 + (c - 48)
        else:
            v = np.int64(_SAT)
    return v


@nb.njit(cache=True, nogil=True)
def _memo_arg(data, p, L, width):
    """The memo index of a GET/PUT-family opcode at p: ``width`` 1 or 4 little-endian bytes, or 0 for a
    decimal line. Returns (index, position after it); index -1 when the data end first, -2 when the line
    is malformed."""
    if width:
        if p + width > L:
            return np.int64(-1), p
        return (np.int64(data[p]) if width == 1 else _uint_le(data, p, 4)), p + width
    e = _line_end(data, p)
    if e < 0:
        return np.int64(-1), p
    idx = _digits(data, p, e)
    if idx < 0:
        return np.int64(-2), p
    return idx, e + 1


@nb.njit(cache=True, nogil=True)
def _equals(data, p, n, blob, q, m):
    if n != m:
        return False
    for i in range(n):
        if data[p + i] != blob[q + i]:
            return False
    return True


@nb.njit(cache=True, nogil=True)
def _find_global(data, mp, ml, np_, nl, gblob, gtab):
    for g in range(gtab.shape[0]):
        if _equals(data, mp, ml, gblob, gtab[g, 0], gtab[g, 1]) and \
                _equals(data, np_, nl, gblob, gtab[g, 2], gtab[g, 3]):
            return g
    return -1


@nb.njit(cache=True, nogil=True)
def _dtype_row(data, q, n, dblob, dtab):
    """The dtype-table row for the code data[q:q+n], or -1."""
    for r in range(dtab.shape[0]):
        if dtab[r, D_ITEMSIZE] >= 0:
            if _equals(data, q, n, dblob, dtab[r, D_OFF], dtab[r, D_LEN]):
                return r
        elif 2 <= n <= 11 and data[q] == dtab[r, D_KIND]:
            ok, v = _decimal(data, q + 1, q + n, False)
            if ok:
                return r
    return -1


@nb.njit(cache=True, nogil=True)
def _latin1_name(data, p, n):
    """data[p:p+n], lowercased with '_' as '-', is latin1, latin-1 or iso-8859-1."""
    if n != 6 and n != 7 and n != 10:
        return False
    lit = "iso-8859-1" if n == 10 else ("latin-1" if n == 7 else "latin1")
    for i in range(n):
        c = np.int64(data[p + i])
        if 65 <= c <= 90:
            c += 32
        elif c == 95:
            c = 45
        if c != ord(lit[i]):
            return False
    return True


@nb.njit(cache=True, nogil=True, inline="always")
def _shape(nodes, ch, s):
    """(status, ndim, count) of a shape node: status 0 ok, 1 not a tuple of at most 64 items, 2 a bad
    dimension; count saturates at _SAT (callers report an overflow as a size mismatch)."""
    if (nodes[s, W] & KIND_MASK) != K_TUPLE or nodes[s, B] > _MAX_DIMS:
        return 1, np.int64(0), np.int64(0)
    c0 = nodes[s, A]
    nd = nodes[s, B]
    count = np.int64(1)
    zero = False
    for i in range(nd):
        d = ch[c0 + i]
        w = nodes[d, W]
        v = nodes[d, V]
        if (w & KIND_MASK) != K_INT or (w & F_BOOL) != 0 or v < 0:
            return 2, nd, np.int64(0)
        if v == 0:
            zero = True
        elif count < _SAT:
            if count > _SAT // v:
                count = np.int64(_SAT)
            else:
                count *= v
    if zero:
        count = np.int64(0)
    return 0, nd, count


@nb.njit(cache=True, nogil=True, inline="always")
def _is_char(data, nodes, s, c):
    """Node s is a str whose content is the single ASCII character c."""
    w = nodes[s, W]
    return (w & KIND_MASK) == K_STR and (w & F_CONTENT) != 0 and nodes[s, B] == 1 and data[nodes[s, A]] == c


@nb.njit(cache=True, nogil=True)
def _run(data, gblob, gtab, dblob, dtab, max_depth, nodes, ch, stack, marks, memo, gseq, st, progress):
    """One round of the scan, from st[S_POS] until the pickle is done or an array needs more room."""
    L = data.shape[0]
    pos = st[S_POS]
    nn = st[S_NN]
    nch = st[S_NCH]
    sp = st[S_SP]
    nmarks = st[S_NMARKS]
    fence = st[S_FENCE]
    memo_len = st[S_MEMO_LEN]
    memo_writes = st[S_MEMO_WRITES]
    memo_init = st[S_MEMO_INIT]
    ngseq = st[S_NGSEQ]
    budget = st[S_BUDGET]
    key_budget = st[S_KEYS]
    ncap = nodes.shape[0]
    scap = stack.shape[0]
    err = E_TRUNC
    i0 = np.int64(0)
    i1 = np.int64(0)
    i2 = np.int64(0)
    result = np.int64(-1)
    need = np.int64(0)
    ret = _DONE
    opos = pos
    next_publish = pos
    complete = False  # every opcode read whole, but no STOP
    while True:
        if pos >= L:
            complete = True
            break
        opos = pos
        if pos >= next_publish:  # every opcode before pos is checked
            _store_release(progress, 0, pos)
            next_publish = pos + _PUBLISH_EVERY
            if _load_acquire(progress, 1) != 0:
                err = E_CANCELLED
                break
        if nn + 2 > ncap:
            ret = _NEED_NODES
            break
        if sp + 2 > scap:
            ret = _NEED_STACK
            break
        op = np.int64(data[pos])
        p = pos + 1
        new = -1  # kind of a new node to push (its W flags, V, A, B below)
        push = np.int64(-1)  # or an existing node to push
        nflags = np.int64(0)
        nv = np.int64(0)
        na = np.int64(0)
        nb_ = np.int64(0)
        # ------------------------------------------------------------------ memo
        if op == 0x94:  # MEMOIZE
            if sp <= fence:
                err = E_UNDERFLOW
                break
            idx = memo_len
            if idx >= memo.shape[0]:
                ret = _NEED_MEMO
                need = idx + 1
                break
            memo_writes += 1
            while memo_init <= idx:
                memo[memo_init] = -1
                memo_init += 1
            if memo[idx] < 0:
                memo_len += 1
            memo[idx] = stack[sp - 1]
            pos = p
            continue
        elif op == 0x68 or op == 0x6a or op == 0x67:  # BINGET, LONG_BINGET, GET
            idx, nxt = _memo_arg(data, p, L, 1 if op == 0x68 else (4 if op == 0x6a else 0))
            if idx == -1:
                break
            if idx == -2:
                err = E_BADARG
                break
            pos = nxt
            if idx >= memo_init or memo[idx] < 0:
                err = E_MEMO
                i0 = idx
                break
            stack[sp] = memo[idx]
            sp += 1
            continue
        elif op == 0x71 or op == 0x72 or op == 0x70:  # BINPUT, LONG_BINPUT, PUT
            idx, nxt = _memo_arg(data, p, L, 1 if op == 0x71 else (4 if op == 0x72 else 0))
            if idx == -1:
                break
            if idx == -2:
                err = E_BADARG
                break
            if sp <= fence:
                err = E_UNDERFLOW
                break
            if idx > memo_writes + 1024:
                err = E_MEMO_RANGE
                i0 = idx
                break
            if idx >= memo.shape[0]:
                ret = _NEED_MEMO
                need = idx + 1
                break
            memo_writes += 1
            while memo_init <= idx:
                memo[memo_init] = -1
                memo_init += 1
            if memo[idx] < 0:
                memo_len += 1
            memo[idx] = stack[sp - 1]
            pos = nxt
            continue
        # ------------------------------------------------------------------ ints, tuples, MARK
        elif op == 0x4b:  # BININT1: the nodes of 0..255 are made once
            if p + 1 > L:
                break
            push = _SMALL_INTS + np.int64(data[p])
            pos = p + 1
        elif op == 0x4d:  # BININT2
            if p + 2 > L:
                break
            new = K_INT
            nv = _uint_le(data, p, 2)
            pos = p + 2
        elif op == 0x4a:  # BININT
            if p + 4 > L:
                break
            new = K_INT
            nv = _uint_le(data, p, 4)
            if nv >= 1 << 31:
                nv -= 1 << 32
            elif nv < 256:
                new = -1
                push = _SMALL_INTS + nv
            pos = p + 4
        elif op == 0x85 or op == 0x86 or op == 0x87 or op == 0x74 or op == 0x29:
            # TUPLE1, TUPLE2, TUPLE3, TUPLE (to the MARK), EMPTY_TUPLE
            if op == 0x74:
                if nmarks < 1:
                    err = E_NOMARK
                    break
                start = marks[nmarks - 1]
            else:
                n = 0 if op == 0x29 else op - 0x84
                if sp < n or sp - n < fence:
                    err = E_UNDERFLOW
                    break
                start = sp - n
            n = sp - start
            if nch + n > ch.shape[0]:
                ret = _NEED_CH
                need = nch + n
                break
            if op == 0x74:
                nmarks -= 1
                fence = marks[nmarks - 1] if nmarks > 0 else 0
            depth = np.int64(0)
            tsize = min(n, _TSIZE_SAT)
            tflags = np.int64(0)
            for i in range(n):
                c = stack[start + i]
                ch[nch + i] = c
                w = nodes[c, W]
                ck = w & KIND_MASK
                d = (w & DEPTH_MASK) >> DEPTH_SHIFT
                if d > depth:
                    depth = d
                if ck == K_TUPLE:
                    tsize = min(tsize + nodes[c, V], _TSIZE_SAT)  # each term <= 2**40: no overflow
                    tflags |= w & (F_GLOBALISH | F_UNHASHABLE)
                else:
                    if ck == K_GLOBAL:
                        tflags |= F_GLOBALISH
                    if ((1 << ck) & _HASHABLE_KINDS) == 0:
                        tflags |= F_UNHASHABLE
                    if ((1 << ck) & _MUTABLE_KINDS) != 0:
                        nodes[c, W] = w | F_PLACED
            depth += 1
            if depth > max_depth:
                err = E_DEPTH
                break
            t = nn
            nn += 1
            nodes[t, W] = K_TUPLE | tflags | (op << OP_SHIFT) | (depth << DEPTH_SHIFT)
            nodes[t, V] = tsize
            nodes[t, A] = nch
            nodes[t, B] = n
            nch += n
            sp = start
            stack[sp] = t
            sp += 1
            pos = p
            continue
        elif op == 0x28:  # MARK
            if nmarks >= marks.shape[0]:
                ret = _NEED_MARKS
                break
            marks[nmarks] = sp
            nmarks += 1
            fence = sp
            pos = p
            continue
        elif op == 0x4e:  # NONE
            push = 0
            pos = p
        elif op == 0x88:  # NEWTRUE
            push = 1
            pos = p
        elif op == 0x89:  # NEWFALSE
            push = 2
            pos = p
        # ------------------------------------------------------------------ calls and BUILD
        elif op == 0x52:  # REDUCE
            if sp - 2 < fence:
                err = E_UNDERFLOW
                break
            args = stack[sp - 1]
            fnode = stack[sp - 2]
            if (nodes[fnode, W] & KIND_MASK) != K_GLOBAL or gtab[nodes[fnode, V], 4] == FN_NDARRAY:
                err = E_CALL
                i0 = fnode
                break
            fn = gtab[nodes[fnode, V], 4]
            if (nodes[args, W] & KIND_MASK) != K_TUPLE:
                err = E_NOT_TUPLE
                break
            c0 = nodes[args, A]
            nargs = nodes[args, B]
            a0 = ch[c0] if nargs > 0 else 0
            a1 = ch[c0 + 1] if nargs > 1 else 0
            a2 = ch[c0 + 2] if nargs > 2 else 0
            a3 = ch[c0 + 3] if nargs > 3 else 0
            k0 = nodes[a0, W] & KIND_MASK
            k1 = nodes[a1, W] & KIND_MASK
            k2 = nodes[a2, W] & KIND_MASK
            bad = OK
            spend = np.int64(0)
            if fn == FN_RECONSTRUCT:
                new = K_SHELL
                if nargs != 3:
                    bad = E_HEADER
                elif k0 != K_GLOBAL or gtab[nodes[a0, V], 4] != FN_NDARRAY:
                    bad = E_SUBTYPE
                    i0 = a0
                else:
                    status, nd, count = _shape(nodes, ch, a1)
                    w2 = nodes[a2, W]
                    tlen = nodes[a2, V] if k2 == K_BYTES else nodes[a2, B]
                    if status != 0 or count != 0 or (k2 != K_BYTES and k2 != K_STR) or \
                            (w2 & F_CONTENT) == 0 or tlen != 1 or data[nodes[a2, A]] != 98:  # b"b"
                        bad = E_HEADER
            elif fn == FN_DTYPE:
                new = K_DTYPE
                row = -1
                if nargs == 3 and k0 == K_STR and (nodes[a0, W] & F_CONTENT) != 0:
                    row = _dtype_row(data, nodes[a0, A], nodes[a0, B], dblob, dtab)
                if nargs != 3:
                    bad = E_DTYPE_ARGS
                elif row < 0:
                    bad = E_DTYPE_CODE
                    i0 = a0
                elif (nodes[a1, W] & F_BOOL) == 0 or (nodes[a2, W] & F_BOOL) == 0 or nodes[a2, V] != 1:
                    bad = E_DTYPE_ARGS  # (code, align: bool, copy=True), as numpy writes it
                else:
                    nv = dtab[row, D_ITEMSIZE]
                    na = dtab[row, D_KIND]
                    nb_ = row
            elif fn == FN_SCALAR:
                new = K_SCALAR
                if nargs != 2:
                    bad = E_ARGS
                elif k0 != K_DTYPE:
                    bad = E_NOT_DTYPE
                elif (nodes[a0, W] & F_BUILT) == 0:
                    bad = E_INCOMPLETE
                elif nodes[a0, A] == 79:  # 'O'
                    bad = E_SCALAR_OBJ
                elif k1 != K_BYTES or (nodes[a1, W] & F_EXACT) == 0 or nodes[a1, V] != nodes[a0, V]:
                    bad = E_SCALAR
                else:
                    spend = nodes[a0, V]
            elif fn == FN_FROMBUFFER:
                new = K_ARRAY
                nflags = F_BUILT
                if nargs != 4 and nargs != 5:
                    bad = E_ARGS
                elif k1 != K_DTYPE:
                    bad = E_NOT_DTYPE
                elif (nodes[a1, W] & F_BUILT) == 0:
                    bad = E_INCOMPLETE
                elif nodes[a1, A] == 79:
                    bad = E_FROMBUF_OBJ
                else:
                    status, nd, count = _shape(nodes, ch, a2)
                    if status != 0:
                        bad = E_SHAPE
                    elif (k0 != K_BYTES and k0 != K_BYTEARRAY) or (nodes[a0, W] & F_EXACT) == 0:
                        bad = E_RAWTYPE
                    elif nargs == 4:
                        if not (_is_char(data, nodes, a3, 67) or _is_char(data, nodes, a3, 70)):  # C, F
                            bad = E_ORDER
                    else:  # order 'K' with the axis order that makes the buffer C-contiguous
                        a4 = ch[c0 + 4]
                        if not _is_char(data, nodes, a3, 75) or (nodes[a4, W] & KIND_MASK) != K_TUPLE or \
                                nodes[a4, B] != nd:
                            bad = E_ORDER
                        else:
                            seen = np.int64(0)
                            for i in range(nd):
                                d = ch[nodes[a4, A] + i]
                                v = nodes[d, V]
                                if (nodes[d, W] & KIND_MASK) != K_INT or v < 0 or v >= nd or \
                                        ((seen >> v) & 1) != 0:
                                    bad = E_ORDER
                                    break
                                seen |= np.int64(1) << v
                    if bad == OK:
                        isz = nodes[a1, V]
                        nbytes = np.int64(_SAT) if count >= _SAT // max(isz, 1) else count * isz
                        if nbytes != nodes[a0, V]:
                            bad = E_SIZE
                            i0 = a2
                            i1 = a1
                            i2 = nodes[a0, V]
                        else:
                            spend = max(nbytes, count)
            elif fn == FN_ENCODE:
                new = K_BYTES
                good = (nargs == 2 or nargs == 3) and k0 == K_STR and k1 == K_STR and \
                    (nodes[a1, W] & F_CONTENT) != 0 and _latin1_name(data, nodes[a1, A], nodes[a1, B]) and \
                    (nargs == 2 or k2 == K_STR)
                if not good:
                    bad = E_ENCODE
                else:
                    w0 = nodes[a0, W]
                    nflags = w0 & F_EXACT
                    if (w0 & F_CONTENT) != 0 and (w0 & F_ASCII) != 0:
                        nflags |= F_CONTENT
                    nv = nodes[a0, V]
                    na = nodes[a0, A]
                    nb_ = nodes[a0, B]
                    spend = nodes[a0, B]
            elif fn == FN_ODICT:
                new = K_ODICT
                if nargs != 0:
                    bad = E_ODICT_ARGS
            elif fn == FN_BYTES:
                new = K_BYTES
                nflags = F_EXACT | F_CONTENT
                if nargs != 0:
                    bad = E_BYTES_ARGS
            else:
                bad = E_CALL
                i0 = fnode
            if bad != OK:
                err = bad
                break
            budget -= spend
            if budget < 0:
                err = E_BUDGET
                break
            sp -= 2
            pos = p
        elif op == 0x62:  # BUILD
            if sp - 2 < fence:
                err = E_UNDERFLOW
                break
            state = stack[sp - 1]
            inst = stack[sp - 2]
            iw = nodes[inst, W]
            ik = iw & KIND_MASK
            if (ik != K_SHELL and ik != K_DTYPE) or (iw & F_BUILT) != 0:
                err = E_BUILD
                i0 = inst
                break
            bad = OK
            spend = np.int64(0)
            c0 = nodes[state, A]
            ns = nodes[state, B]
            if (nodes[state, W] & KIND_MASK) != K_TUPLE:
                bad = E_DTYPE_STATE if ik == K_DTYPE else E_ARRSTATE
            elif ik == K_DTYPE:  # exactly (3, byteorder, None, None, None, elsize, alignment, flags)
                row = nodes[inst, B]
                if ns != 8:
                    bad = E_DTYPE_STATE
                else:
                    s0 = ch[c0]
                    s1 = ch[c0 + 1]
                    s5 = ch[c0 + 5]
                    s6 = ch[c0 + 6]
                    s7 = ch[c0 + 7]
                    w5 = nodes[s5, W]
                    bo = -1
                    if _is_char(data, nodes, s1, 60):  # <
                        bo = 0
                    elif _is_char(data, nodes, s1, 62):  # >
                        bo = 1
                    elif _is_char(data, nodes, s1, 124):  # |
                        bo = 2
                    if (nodes[s0, W] & KIND_MASK) != K_INT or nodes[s0, V] != 3 or bo < 0 or \
                            ((dtab[row, D_BO] >> bo) & 1) == 0 or \
                            ch[c0 + 2] != 0 or ch[c0 + 3] != 0 or ch[c0 + 4] != 0 or \
                            (w5 & KIND_MASK) != K_INT or (w5 & F_BOOL) != 0 or \
                            (nodes[s6, W] & KIND_MASK) != K_INT or (nodes[s7, W] & KIND_MASK) != K_INT or \
                            nodes[s6, V] != dtab[row, D_ALIGN] or nodes[s7, V] != dtab[row, D_FLAGS]:
                        bad = E_DTYPE_STATE
                    elif dtab[row, D_ITEMSIZE] >= 0:
                        if nodes[s5, V] != dtab[row, D_ELSIZE]:
                            bad = E_DTYPE_STATE
                    else:  # str / bytes: the state gives the size
                        el = nodes[s5, V]
                        per = 4 if dtab[row, D_KIND] == 85 else 1
                        if el < 0 or el % per != 0 or el > (1 << 31):
                            bad = E_DTYPE_SIZE
                            i1 = el
                        else:
                            nodes[inst, V] = el
            else:  # array: (1, shape, dtype, fortran, data) or (shape, dtype, fortran, data)
                off = ns - 4
                if (ns != 4 and ns != 5) or (ns == 5 and ((nodes[ch[c0], W] & KIND_MASK) != K_INT or
                                                          nodes[ch[c0], V] != 1)):
                    bad = E_ARRSTATE
                else:
                    shp = ch[c0 + off]
                    dt = ch[c0 + off + 1]
                    fo = ch[c0 + off + 2]
                    raw = ch[c0 + off + 3]
                    dw = nodes[dt, W]
                    rw = nodes[raw, W]
                    status, nd, count = _shape(nodes, ch, shp)
                    if status != 0:
                        bad = E_SHAPE
                    elif (dw & KIND_MASK) != K_DTYPE:
                        bad = E_NOT_DTYPE
                    elif (dw & F_BUILT) == 0:
                        bad = E_INCOMPLETE
                    elif (nodes[fo, W] & KIND_MASK) != K_INT or nodes[fo, V] < 0 or nodes[fo, V] > 1:
                        bad = E_ORDER
                    elif nodes[dt, A] == 79:  # object array: a list of plain items
                        if (rw & KIND_MASK) != K_LIST or nodes[raw, V] != count:
                            bad = E_LIST
                            i1 = shp
                        elif (rw & F_ALLLEAF) == 0:
                            bad = E_OBJ_ITEMS
                        else:
                            spend = count * 8
                            nodes[raw, W] = rw | F_PLACED
                    elif (rw & KIND_MASK) != K_BYTES or (rw & F_EXACT) == 0:
                        bad = E_RAWTYPE
                    else:
                        isz = nodes[dt, V]
                        nbytes = np.int64(_SAT) if count >= _SAT // max(isz, 1) else count * isz
                        if nbytes != nodes[raw, V]:
                            bad = E_SIZE
                            i0 = shp
                            i1 = dt
                            i2 = nodes[raw, V]
                        else:
                            spend = max(nbytes, count)
            if bad != OK:
                err = bad
                if i0 == 0:
                    i0 = inst
                break
            budget -= spend
            if budget < 0:
                err = E_BUDGET
                break
            nodes[inst, W] = iw | F_BUILT
            sp -= 1
            pos = p
            continue
        # ------------------------------------------------------------------ strings and bytes
        elif op == 0x43 or op == 0x42 or op == 0x8e or op == 0x96:
            # SHORT_BINBYTES, BINBYTES, BINBYTES8, BYTEARRAY8
            wd = 1 if op == 0x43 else (4 if op == 0x42 else 8)
            if p + wd > L:
                break
            n = _size_le(data, p, wd)
            if n < 0 or n > L - p - wd:
                break
            new = K_BYTEARRAY if op == 0x96 else K_BYTES
            nflags = F_EXACT | F_CONTENT
            nv = n
            na = p + wd
            nb_ = n
            pos = p + wd + n
        elif op == 0x8c or op == 0x58 or op == 0x8d or op == 0x55 or op == 0x54:
            # SHORT_BINUNICODE, BINUNICODE, BINUNICODE8 (utf-8); SHORT_BINSTRING, BINSTRING (ASCII)
            wd = 1 if (op == 0x8c or op == 0x55) else (8 if op == 0x8d else 4)
            if p + wd > L:
                break
            n = _size_le(data, p, wd)
            if n < 0 or n > L - p - wd:
                break
            q = p + wd
            chars = np.int64(0)
            nonascii = 0
            for i in range(q, q + n):
                c = data[i]
                nonascii |= c
                if c < 0x80 or c >= 0xC0:  # a character starts here (utf-8)
                    chars += 1
            if op == 0x55 or op == 0x54:
                chars = n
            new = K_STR
            nflags = F_EXACT | F_CONTENT | (F_ASCII if nonascii < 0x80 else 0)
            nv = chars
            na = q
            nb_ = n
            pos = q + n
        elif op == 0x56:  # UNICODE: a raw-unicode-escape line
            e = _line_end(data, p)
            if e < 0:
                break
            chars = np.int64(0)
            nonascii = 0
            escaped = False
            i = p
            while i < e:
                c = data[i]
                if c == 92:  # backslash: \uXXXX and \UXXXXXXXX are one character, others two
                    escaped = True
                    if i + 1 >= e:
                        chars = -1
                        break
                    elif data[i + 1] == 117:
                        chars += 1
                        i += 6
                    elif data[i + 1] == 85:
                        chars += 1
                        i += 10
                    else:
                        chars += 2
                        i += 2
                else:
                    nonascii |= c
                    chars += 1
                    i += 1
            new = K_STR
            if chars >= 0 and i == e:
                nflags = F_EXACT
            if not escaped:
                nflags |= F_CONTENT
            if nonascii < 0x80:
                nflags |= F_ASCII
            nv = chars
            na = p
            nb_ = e - p
            pos = e + 1
        elif op == 0x53:  # STRING: a quoted, escaped line, decoded as ASCII
            e = _line_end(data, p)
            if e < 0:
                break
            n = e - p
            if n < 2 or data[p] != data[e - 1] or (data[p] != 39 and data[p] != 34):
                err = E_BADARG
                break
            escaped = False
            nonascii = 0
            for i in range(p + 1, e - 1):
                nonascii |= data[i]
                if data[i] == 92:
                    escaped = True
            new = K_STR
            if not escaped:
                nflags = F_EXACT | F_CONTENT | (F_ASCII if nonascii < 0x80 else 0)
            nv = n - 2
            na = p + 1
            nb_ = n - 2
            pos = e + 1
        # ------------------------------------------------------------------ other leaves
        elif op == 0x47:  # BINFLOAT
            if p + 8 > L:
                break
            new = K_FLOAT
            pos = p + 8
        elif op == 0x46:  # FLOAT
            e = _line_end(data, p)
            if e < 0:
                break
            if e == p:
                err = E_BADARG
                break
            new = K_FLOAT
            pos = e + 1
        elif op == 0x49 or op == 0x4c:  # INT, LONG
            e = _line_end(data, p)
            if e < 0:
                break
            if e == p:
                err = E_BADARG
                break
            q = e
            if op == 0x4c and data[e - 1] == 76:  # the trailing 'L'
                q = e - 1
            if op == 0x49 and e - p == 2 and data[p] == 48 and (data[p + 1] == 48 or data[p + 1] == 49):
                ok = True  # I00 / I01: False / True
                nv = np.int64(data[p + 1]) - 48
                nflags = F_BOOL
            else:
                ok, nv = _decimal(data, p, q, True)
            new = K_INT if ok else K_BIGINT
            pos = e + 1
        elif op == 0x8a or op == 0x8b:  # LONG1, LONG4
            wd = 1 if op == 0x8a else 4
            if p + wd > L:
                break
            n = _uint_le(data, p, wd)
            if op == 0x8b and n >= 1 << 31:
                err = E_BADARG
                break
            if n > L - p - wd:
                break
            q = p + wd
            if n <= 8:
                v = np.int64(0)
                for i in range(n):
                    v |= np.int64(data[q + i]) << (8 * i)
                if 0 < n < 8 and data[q + n - 1] >= 128:
                    v -= np.int64(1) << (8 * n)
                new = K_INT
                nv = v
            else:
                new = K_BIGINT
            pos = q + n
        # ------------------------------------------------------------------ containers
        elif op == 0x5d or op == 0x7d or op == 0x8f:  # EMPTY_LIST, EMPTY_DICT, EMPTY_SET
            new = K_LIST if op == 0x5d else (K_DICT if op == 0x7d else K_SET)
            nflags = F_ALLLEAF
            pos = p
        elif op == 0x61 or op == 0x65 or op == 0x73 or op == 0x75 or op == 0x90:
            # APPEND, APPENDS, SETITEM, SETITEMS, ADDITEMS
            if op == 0x61:
                x = sp - 1
                xfence = fence
            elif op == 0x73:
                x = sp - 2
                xfence = fence
            else:
                if nmarks < 1:
                    err = E_NOMARK
                    break
                x = marks[nmarks - 1]
                xfence = marks[nmarks - 2] if nmarks > 1 else 0
            if x > sp or x <= xfence:
                err = E_UNDERFLOW
                break
            tgt = stack[x - 1]
            tw = nodes[tgt, W]
            tk = tw & KIND_MASK
            if op == 0x61 or op == 0x65:
                good = tk == K_LIST
            elif op == 0x90:
                good = tk == K_SET
            else:
                good = tk == K_DICT or tk == K_ODICT
            if not good:
                err = E_TARGET
                i0 = tgt
                break
            if (tw & F_PLACED) != 0:
                err = E_CHANGED
                break
            keyed = op == 0x73 or op == 0x75
            if keyed and (sp - x) % 2 != 0:
                err = E_ODD
                break
            depth = (tw & DEPTH_MASK) >> DEPTH_SHIFT
            bad = OK
            for i in range(x, sp):
                c = stack[i]
                w = nodes[c, W]
                ck = w & KIND_MASK
                if c == tgt:
                    bad = E_CHANGED
                    break
                if (w & F_GLOBALISH) != 0:
                    bad = E_GLOBAL_VALUE
                    i0 = c
                    break
                if op == 0x90 or (keyed and (i - x) % 2 == 0):  # hashed
                    if ((1 << ck) & _HASHABLE_KINDS) == 0 or (w & F_UNHASHABLE) != 0:
                        bad = E_UNHASHABLE
                        i0 = c
                        break
                    if ck == K_TUPLE:
                        key_budget -= nodes[c, V]
                        if key_budget < 0:
                            bad = E_KEYS
                            break
                if ((1 << ck) & _LEAF_KINDS) == 0:
                    tw &= ~F_ALLLEAF
                if ((1 << ck) & _MUTABLE_KINDS) != 0:
                    nodes[c, W] = w | F_PLACED
                d = ((w & DEPTH_MASK) >> DEPTH_SHIFT) + 1
                if d > depth:
                    depth = d
            if bad != OK:
                err = bad
                break
            if depth > max_depth:
                err = E_DEPTH
                break
            if op != 0x61 and op != 0x73:
                nmarks -= 1
                fence = xfence
            nodes[tgt, W] = (tw & ~DEPTH_MASK) | (depth << DEPTH_SHIFT)
            nodes[tgt, V] += (sp - x) // 2 if keyed else sp - x
            sp = x
            pos = p
            continue
        elif op == 0x6c or op == 0x64 or op == 0x91:  # LIST, DICT, FROZENSET
            if nmarks < 1:
                err = E_NOMARK
                break
            start = marks[nmarks - 1]
            keyed = op == 0x64
            if keyed and (sp - start) % 2 != 0:
                err = E_ODD
                break
            depth = np.int64(0)
            lflags = F_ALLLEAF
            bad = OK
            for i in range(start, sp):
                c = stack[i]
                w = nodes[c, W]
                ck = w & KIND_MASK
                if (w & F_GLOBALISH) != 0:
                    bad = E_GLOBAL_VALUE
                    i0 = c
                    break
                if op == 0x91 or (keyed and (i - start) % 2 == 0):  # hashed
                    if ((1 << ck) & _HASHABLE_KINDS) == 0 or (w & F_UNHASHABLE) != 0:
                        bad = E_UNHASHABLE
                        i0 = c
                        break
                    if ck == K_TUPLE:
                        key_budget -= nodes[c, V]
                        if key_budget < 0:
                            bad = E_KEYS
                            break
                if ((1 << ck) & _LEAF_KINDS) == 0:
                    lflags = 0
                if ((1 << ck) & _MUTABLE_KINDS) != 0:
                    nodes[c, W] = w | F_PLACED
                d = (w & DEPTH_MASK) >> DEPTH_SHIFT
                if d > depth:
                    depth = d
            if bad != OK:
                err = bad
                break
            depth += 1
            if depth > max_depth:
                err = E_DEPTH
                break
            nmarks -= 1
            fence = marks[nmarks - 1] if nmarks > 0 else 0
            t = nn
            nn += 1
            kind = K_LIST if op == 0x6c else (K_DICT if keyed else K_FROZENSET)
            nodes[t, W] = kind | (lflags if kind == K_LIST else 0) | (op << OP_SHIFT) | (depth << DEPTH_SHIFT)
            nodes[t, V] = (sp - start) // 2 if keyed else sp - start
            nodes[t, A] = 0
            nodes[t, B] = 0
            sp = start
            stack[sp] = t
            sp += 1
            pos = p
            continue
        # ------------------------------------------------------------------ stack, framing, STOP
        elif op == 0x30:  # POP: the topmost MARK if it is at the top, else the topmost object
            if nmarks > 0 and marks[nmarks - 1] == sp:
                nmarks -= 1
                fence = marks[nmarks - 1] if nmarks > 0 else 0
            elif sp <= fence:
                err = E_UNDERFLOW
                break
            else:
                sp -= 1
            pos = p
            continue
        elif op == 0x31:  # POP_MARK
            if nmarks < 1:
                err = E_NOMARK
                break
            nmarks -= 1
            if marks[nmarks] < sp:
                sp = marks[nmarks]
            fence = marks[nmarks - 1] if nmarks > 0 else 0
            pos = p
            continue
        elif op == 0x32:  # DUP
            if sp <= fence:
                err = E_UNDERFLOW
                break
            push = stack[sp - 1]
            pos = p
        elif op == 0x80:  # PROTO
            if p + 1 > L:
                break
            if data[p] > 5:
                err = E_BADARG
                break
            pos = p + 1
            continue
        elif op == 0x95:  # FRAME: a buffering hint; the C unpickler needs the whole frame to be there
            if p + 8 > L:
                break
            n = _size_le(data, p, 8)
            if n < 0 or n > L - p - 8:
                break
            pos = p + 8
            continue
        elif op == 0x2e:  # STOP
            if sp <= fence:
                err = E_UNDERFLOW
                break
            result = stack[sp - 1]
            if (nodes[result, W] & F_GLOBALISH) != 0:
                err = E_GLOBAL_VALUE
                i0 = result
                break
            err = OK
            break
        elif op == 0x63 or op == 0x93:  # GLOBAL, STACK_GLOBAL
            if ngseq >= gseq.shape[0]:
                err = E_GLOBALS
                break
            if op == 0x63:
                e1 = _line_end(data, p)
                if e1 < 0:
                    break
                e2 = _line_end(data, e1 + 1)
                if e2 < 0:
                    break
                if e1 == p or e2 == e1 + 1:
                    err = E_BADARG
                    break
                g = _find_global(data, p, e1 - p, e1 + 1, e2 - e1 - 1, gblob, gtab)
                if g < 0:
                    err = E_GLOBAL
                    i1 = p
                    i2 = e1 + 1
                    break
                pos = e2 + 1
            else:
                if sp - 2 < fence:
                    err = E_UNDERFLOW
                    break
                mnode = stack[sp - 2]
                gnode = stack[sp - 1]
                mw = nodes[mnode, W]
                gw = nodes[gnode, W]
                if (mw & KIND_MASK) != K_STR or (gw & KIND_MASK) != K_STR:
                    err = E_BADARG
                    break
                g = -1
                if (mw & F_CONTENT) != 0 and (gw & F_CONTENT) != 0:
                    g = _find_global(data, nodes[mnode, A], nodes[mnode, B], nodes[gnode, A], nodes[gnode, B],
                                     gblob, gtab)
                if g < 0:
                    err = E_GLOBAL
                    i0 = 1
                    i1 = mnode
                    i2 = gnode
                    break
                sp -= 2
                pos = p
            gseq[ngseq] = g
            ngseq += 1
            new = K_GLOBAL
            nflags = F_GLOBALISH
            nv = g
        # ------------------------------------------------------------------ refused
        elif op == 0x81 or op == 0x92:  # NEWOBJ, NEWOBJ_EX
            err = E_NEWOBJ
            break
        elif op == 0x69 or op == 0x6f:  # INST, OBJ
            err = E_INST
            break
        elif op == 0x82 or op == 0x83 or op == 0x84:  # EXT1, EXT2, EXT4
            err = E_EXT
            break
        elif op == 0x50 or op == 0x51:  # PERSID, BINPERSID
            err = E_PERSID
            break
        elif op == 0x97 or op == 0x98:  # NEXT_BUFFER, READONLY_BUFFER
            err = E_OOB
            break
        else:
            err = E_OPCODE
            i0 = op
            break
        # ------------------------------------------------------------------ push
        if new >= 0:
            t = nn
            nn += 1
            depth = 1 if ((1 << new) & _CONTAINER_KINDS) != 0 else 0
            nodes[t, W] = new | nflags | (op << OP_SHIFT) | (depth << DEPTH_SHIFT)
            nodes[t, V] = nv
            nodes[t, A] = na
            nodes[t, B] = nb_
            push = t
        stack[sp] = push
        sp += 1
    if ret != _DONE:
        pos = opos  # the opcode runs again once there is room
    else:  # done: publish how far the input is good (through STOP, or up to the failing opcode)
        if err == OK:
            _store_release(progress, 0, opos + 1)
        elif complete:
            _store_release(progress, 0, L)
        else:
            _store_release(progress, 0, opos)
        if err == E_TRUNC:
            opos = L
    st[S_POS] = opos if ret == _DONE else pos
    st[S_NN] = nn
    st[S_NCH] = nch
    st[S_SP] = sp
    st[S_NMARKS] = nmarks
    st[S_FENCE] = fence
    st[S_MEMO_LEN] = memo_len
    st[S_MEMO_WRITES] = memo_writes
    st[S_MEMO_INIT] = memo_init
    st[S_NGSEQ] = ngseq
    st[S_BUDGET] = budget
    st[S_KEYS] = key_budget
    st[S_ERR] = err
    st[S_I0] = i0
    st[S_I1] = i1
    st[S_I2] = i2
    st[S_RESULT] = result
    st[S_NEED] = need
    return ret


@nb.njit(cache=True, nogil=True)
def scan(data, gblob, gtab, dblob, dtab, budget, max_depth, key_budget, nodes, ch, memo, gseq, progress):
    """Check the pickle in ``data`` (uint8).

    ``nodes`` (n x 4), ``ch`` and ``memo`` (int64) are room to work in, uninitialised, grown when needed (a
    caller allocating them with numpy gets huge pages); ``gseq`` (int64) receives the allowlist rows of the
    globals in stream order (a pickle with more globals is refused). ``progress`` (int64[2]): the scan
    keeps ``progress[0]`` at the number of bytes checked so far (atomic, release order; read it with
    :func:`validated`), and stops if the caller sets ``progress[1]``.

    Returns ``(code, pos, i0, i1, i2, nodes, ch, ngseq, result)``: ``code`` is OK or an E_* code for the
    opcode at ``pos`` (with details i0..i2); ``ngseq`` the number of globals; ``result`` the node of the
    object STOP returns.
    """
    stack = np.empty(1024, np.int64)
    marks = np.empty(256, np.int64)
    st = np.zeros(N_STATE, np.int64)
    if nodes.shape[0] < _FIRST_NODE + 64:
        nodes = _grow_rows(nodes, _FIRST_NODE + 64)
    for k in range(_FIRST_NODE):  # None, True, False, 0..255
        nodes[k, W] = K_NONE if k == 0 else (K_INT | F_BOOL if k < _SMALL_INTS else K_INT)
        nodes[k, V] = 1 if k == 1 else (k - _SMALL_INTS if k >= _SMALL_INTS else 0)
        nodes[k, A] = 0
        nodes[k, B] = 0
    st[S_NN] = _FIRST_NODE
    st[S_BUDGET] = budget
    st[S_KEYS] = key_budget
    while True:
        r = _run(data, gblob, gtab, dblob, dtab, max_depth, nodes, ch, stack, marks, memo, gseq, st, progress)
        if r == _NEED_NODES:
            nodes = _grow_rows(nodes, st[S_NN] + 2)
        elif r == _NEED_STACK:
            stack = _grow(stack, st[S_SP] + 2, 0)
        elif r == _NEED_CH:
            ch = _grow(ch, st[S_NEED], 0)
        elif r == _NEED_MARKS:
            marks = _grow(marks, st[S_NMARKS] + 1, 0)
        elif r == _NEED_MEMO:
            memo = _grow(memo, st[S_NEED], -1)
        else:
            break
    return (st[S_ERR], st[S_POS], st[S_I0], st[S_I1], st[S_I2], nodes[:st[S_NN]], ch[:st[S_NCH]],
            st[S_NGSEQ], st[S_RESULT])
