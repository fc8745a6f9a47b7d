"""OctoMap 1.10 ``.bt`` / ``.ot`` files and ``octomap_msgs/Octomap`` payloads, byte-exact.

Authority: OctoMap's source (``src/AbstractOcTree.cpp``, ``src/AbstractOccupancyOcTree.cpp``,
``include/octomap/OccupancyOcTreeBase.hxx``, ``OcTreeBaseImpl.hxx``, ``src/ColorOcTree.cpp``)
and ``octomap_msgs/include/octomap_msgs/conversions.h``.

**Header** (both formats; ``\\n`` line ends)::

    # Octomap OcTree binary file        (.bt)   /   # Octomap OcTree file   (.ot)
    # (feel free to add / change comments, but leave the first line as it is!)
    #
    id OcTree
    size <nodes>                         OctoMap size(): every node, inner and root included
    res <resolution>                     C++ ostream default = printf "%g"
    data

Read like ``AbstractOcTree::readHeader``: whitespace-separated tokens, ``#`` comments and
unknown keywords skip to the end of the line, ``data`` ends the header after its line.

**.bt body** (``writeBinaryNode``): for each *inner* node in pre-order, two bytes holding a
2-bit state per child (0 unknown, 1 free leaf, 2 occupied leaf, 3 inner). Writing applies
OctoMap's ``toMaxLikelihood()`` and ``prune()`` first (the latter stops at the first depth
where nothing prunes and never prunes the root). Reading gives free leaves the clamping
minimum and occupied leaves the clamping maximum of ``params`` (``readBinaryNode``).

**.ot body** (``writeNodesRecurs``): for every node in pre-order its payload, then a child
mask byte. Payload: ``OcTree`` and ``OcTreeStamped`` a float32 log-odds (OctoMap does not
serialise the stamp), ``ColorOcTree`` a float32 log-odds and r, g, b bytes (colour is
dropped on reading; our writer writes ``OcTree``). Inner nodes are written as the max of
their children (``updateInnerOccupancy``); reading keeps the leaves' values verbatim and
drops inner values, since a map is its leaves.

**Childless root.** OctoMap never prunes the root, so a tree it built by updates always has
children under the root. A root without children only comes from deleting every leaf
(octomap#106; ``size()`` is then stale and OctoMap's own reader reports a size mismatch for
``.bt``) and is written as ``00 00`` (``.bt``) or value + mask 0 (``.ot``). OctoMap's readers
then report one 2^16-voxel leaf (clamping max for ``.bt``, the stale inner value for ``.ot``)
that no sensor ever measured; reading it as one would turn all unknown space occupied in a
merge. We read a childless root as an **empty map**. Conversely our writers never emit a
childless root: a map holding one depth-0 leaf is written as its 8 depth-1 children, the
tree OctoMap itself would keep (it never prunes the root).

**Messages.** ``octomap_msgs/Octomap`` carries ``binary``, ``id``, ``resolution`` as fields
and only the body in ``data`` (``binaryMapToMsg`` = ``writeBinaryData``, ``fullMapToMsg`` =
``writeData``); an empty tree gives empty data. ``to_bytes(m, binary)`` gives that body
(for ``binary=True`` after maximum likelihood + prune, the compact form the octomap_msgs
docs recommend; the same bytes as the body of ``save(m, "x.bt")``); ``from_bytes`` reads a
body given ``binary`` and ``resolution``, or a whole file image.

**Bad input** raises ``MapFormatError`` (a ``ValueError``) naming the source and byte
offset: truncated data, a corrupt header, child flags that describe no valid depth-16
tree, an inner ``.bt`` node without children, NaN log-odds, a header ``size`` that differs
from the nodes read, an unsupported id, or bytes after the tree (``strict=False`` accepts
the last three like OctoMap, which ignores them for ``.ot`` and message payloads).
Nothing is allocated from a header's claims; all arrays are sized by the data present.
"""

from __future__ import annotations

import array
import math
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .. import map as _map
from .. import morton
from .._fileutil import atomic_output, check_input_file
from ..budget import check_allocation
from . import _preorder
from ._header import (BINARY_FILE_HEADER, FULL_FILE_HEADER, HEADER_WINDOW, MAX_RESOLUTION,
                      MIN_RESOLUTION, Header, format_resolution, header_bytes, parse_header_prefix,
                      parse_legacy)
from .errors import MapFormatError, MapTooLargeError
from ..tree import num_nodes

__all__ = [
    "BINARY_FILE_HEADER",
    "DEFAULT_MAX_LEAVES",
    "READ_BYTES_PER_LEAF",
    "READ_BYTES_PER_RECORD",
    "reading_bytes",
    "MAX_RESOLUTION",
    "MIN_RESOLUTION",
    "FULL_FILE_HEADER",
    "Header",
    "load",
    "save",
    "from_bytes",
    "to_bytes",
    "from_message",
    "to_message_fields",
    "read_header",
    "format_resolution",
    "num_nodes",
    "max_likelihood_prune",
]

BYTES_SOURCE = "<bytes>"

#: ``.ot`` node payload bytes (before the child mask) per supported tree id.
_OT_PAYLOAD = {"OcTree": 4, "OcTreeStamped": 4, "ColorOcTree": 7}
#: Default ``max_leaves`` of the readers (about 4.5 GB of host memory to read; see ``load``).
DEFAULT_MAX_LEAVES = 100_000_000

# 2-bit child states of a .bt record word: bit j of INNER/OCC/FREE set iff child j is such.
_w = np.arange(1 << 16, dtype=np.uint32)
_states = (_w[:, None] >> (2 * np.arange(8, dtype=np.uint32))) & 3
_weights = (1 << np.arange(8)).astype(np.uint32)
_BT_INNER = ((_states == 3) @ _weights).astype(np.uint8)
_BT_OCC = ((_states == 2) @ _weights).astype(np.uint8)
_BT_FREE = ((_states == 1) @ _weights).astype(np.uint8)
_BT_LEAF = _BT_OCC | _BT_FREE
del _w, _states, _weights
#: bit shift of child slot j of a node at depth d: ``j << _CHILD_SHIFT[d]``.
_U64 = np.uint64
_CHILD_SHIFT = np.array([3 * (15 - d) if d < 16 else 0 for d in range(17)], dtype=np.uint64)


# ----------------------------------------------------------------------------- helpers


def _as_uint8(data) -> np.ndarray:
    """bytes-like, ``array('b')``, int8/uint8 arrays or a list of ints (ROS ``int8[]``)."""
    if isinstance(data, np.ndarray):
        if data.dtype not in (np.uint8, np.int8):
            raise TypeError(f"data must hold bytes (int8/uint8), got dtype {data.dtype}")
        return np.ascontiguousarray(data).reshape(-1).view(np.uint8)
    if isinstance(data, (bytes, bytearray, memoryview)):
        return np.frombuffer(data, dtype=np.uint8)
    if isinstance(data, array.array):
        return np.frombuffer(data, dtype=np.uint8) if data.itemsize == 1 else \
            np.asarray(data, dtype=np.int16).astype(np.uint8)
    values = np.asarray(list(data), dtype=np.int64)
    if values.size and (values.min() < -128 or values.max() > 255):
        raise ValueError("data values must be bytes (-128..255)")
    return values.astype(np.uint8)


def _check_resolution(resolution, name="resolution") -> float:
    try:
        r = float(resolution)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number of metres, got {resolution!r}") from None
    if not (math.isfinite(r) and r > 0):
        raise ValueError(f"{name} must be a positive finite number of metres, got {resolution!r}")
    return r


def _params_f32(params) -> dict[str, np.float32]:
    host = (params if params is not None else _map.OccupancyParams()).host()
    return {k: np.float32(v) for k, v in host.items()}


# ----------------------------------------------------------------------------- decoding


def _stream_error(source, start: int, rec_size: int, total: int, err) -> MapFormatError:
    return MapFormatError(source, min(start + err.record * rec_size, total), err.reason)


#: Peak bytes of host memory per record of the stream while parsing its structure
#: (``_preorder.tree_length`` + ``stream_layout``), and per leaf while generating and sorting
#: the leaves (uint64 sort key, int32 code words, depth, log-odds); see ``reading_bytes``.
READ_BYTES_PER_RECORD = 96
READ_BYTES_PER_LEAF = 29


def reading_bytes(records: int, leaves: int) -> int:
    """Peak host bytes to read a tree of ``records`` stream records and ``leaves`` leaves
    into a map (the map's padded arrays included)."""
    cap = _map.bucket_capacity(leaves) if leaves else 0
    return READ_BYTES_PER_RECORD * records + READ_BYTES_PER_LEAF * leaves + 16 * cap


def _check_size(source, records: int, leaves: int, max_leaves: int | None) -> None:
    """Refuse a tree over ``max_leaves`` leaves or over the memory budget, before allocating."""
    limit = DEFAULT_MAX_LEAVES if max_leaves is None else int(max_leaves)
    if leaves > limit:
        raise MapTooLargeError(source, None, f"the tree holds {leaves:,} leaves, over the "
                               f"limit of {limit:,} (max_leaves / --max-leaves raises it)")
    check_allocation(reading_bytes(records, leaves),
                     f"reading {source} ({records:,} nodes, {leaves:,} leaves)")


class _Leaves(NamedTuple):
    """Leaves read from a stream, sorted by code."""

    words: np.ndarray  # (n, 2) int32 two-word Morton codes (``morton.split_codes``)
    depths: np.ndarray  # (n,) uint8 0..16
    log_odds: np.ndarray  # (n,) float32


def _sorted_leaves(key: np.ndarray, value_of_bit) -> _Leaves:
    """``key (n,)`` uint64 = ``code << 8 | depth << 1 | bit`` -> leaves sorted by code, with
    ``log_odds = value_of_bit[bit]``. Sorts ``key`` in place (no index array)."""
    key.sort(kind="stable")  # timsort: the keys come as sorted runs
    words = np.empty((key.size, 2), np.int32)
    np.right_shift(key, _U64(8 + morton.WORD_BITS), out=words[:, 0], casting="unsafe")
    np.right_shift(key, _U64(8), out=words[:, 1], casting="unsafe")
    words[:, 1] &= np.int32(morton.WORD_MASK)
    depths = np.empty(key.size, np.uint8)
    np.right_shift(key, _U64(1), out=depths, casting="unsafe")
    depths &= np.uint8(31)
    bits = np.empty(key.size, np.uint8)
    np.bitwise_and(key, _U64(1), out=bits, casting="unsafe")
    return _Leaves(words, depths, np.asarray(value_of_bit, np.float32)[bits])


def _decode_bt(buf: np.ndarray, start: int, source, params, max_leaves=None):
    """Body of a ``.bt`` at ``buf[start:]`` -> (leaves, nodes, end)."""
    total = buf.size
    n_rec = (total - start) // 2
    if n_rec == 0:
        raise MapFormatError(source, total, "data ends before the root node: truncated")
    words = buf[start: start + 2 * n_rec].view("<u2")
    inner = _BT_INNER[words]
    try:
        length, h = _preorder.tree_length(_preorder.POPCOUNT8[inner])
    except _preorder.StreamError as err:
        raise _stream_error(source, start, 2, total, err) from None
    words, inner = words[:length], inner[:length]
    end = start + 2 * length
    if length == 1 and words[0] == 0:
        # childless root: an emptied tree (see module docstring)
        return _empty_leaves(), 1, end
    empty_rec = np.flatnonzero(words == 0)
    if empty_rec.size:
        raise MapFormatError(source, start + 2 * int(empty_rec[0]),
                             "an inner node has no children (corrupt child flags)")
    either = _BT_LEAF[words]
    n_leaves = int(_preorder.POPCOUNT8[either].sum(dtype=np.int64))
    _check_size(source, length, n_leaves, max_leaves)
    try:
        lay = _preorder.stream_layout(inner, h, max_depth=15)
    except _preorder.StreamError as err:
        raise _stream_error(source, start, 2, total, err) from None
    del h, inner
    occ = _BT_OCC[words]
    # leaf children, one (parent depth, slot) at a time, as sort keys code << 8 | depth << 1 | occ
    key = np.empty(n_leaves, np.uint64)
    pos = 0
    for d in range(16):
        recs = lay.order[lay.bounds[d]: lay.bounds[d + 1]]
        if recs.size == 0:
            continue
        rec_either, rec_occ, rec_code = either[recs], occ[recs], lay.code[recs]
        for j in range(8):
            sel = np.flatnonzero((rec_either >> j) & 1)
            k = sel.size
            if not k:
                continue
            part = key[pos: pos + k]
            np.bitwise_or(rec_code[sel], _U64(j) << _CHILD_SHIFT[d], out=part)
            part <<= _U64(8)
            part |= _U64((d + 1) << 1) | ((rec_occ[sel] >> j) & 1).astype(np.uint64)
            pos += k
    del lay, occ, either
    p = _params_f32(params)
    leaves = _sorted_leaves(key, [p["clamp_min_log_odds"], p["clamp_max_log_odds"]])
    return leaves, length + n_leaves, end


def _decode_ot(buf: np.ndarray, start: int, source, tree_id: str, max_leaves=None):
    """Body of a ``.ot`` at ``buf[start:]`` -> (leaves, nodes, end)."""
    if tree_id not in _OT_PAYLOAD:
        raise MapFormatError(source, None, f"unsupported octree id {tree_id!r}: can read "
                             f"{', '.join(sorted(_OT_PAYLOAD))} (.ot) and any occupancy "
                             "tree as .bt")
    rec_size = _OT_PAYLOAD[tree_id] + 1
    total = buf.size
    n_rec = (total - start) // rec_size
    if n_rec == 0:
        raise MapFormatError(source, total, "data ends before the root node: truncated")
    recs = buf[start: start + rec_size * n_rec].reshape(n_rec, rec_size)
    mask = recs[:, rec_size - 1]
    try:
        length, h = _preorder.tree_length(_preorder.POPCOUNT8[mask])
    except _preorder.StreamError as err:
        raise _stream_error(source, start, rec_size, total, err) from None
    end = start + rec_size * length
    if length == 1:  # childless root: an emptied tree (see module docstring)
        return _empty_leaves(), 1, end
    mask = mask[:length]
    leaf = np.flatnonzero(mask == 0)
    _check_size(source, length, int(leaf.size), max_leaves)
    # float32 payloads sit at a 5- (or 8-) byte stride: a strided (unaligned) view, no copy
    all_log_odds = np.ndarray((length,), dtype="<f4", buffer=buf, offset=start,
                              strides=(rec_size,))
    log_odds = all_log_odds[leaf]
    bad = np.flatnonzero(np.isnan(log_odds))
    if bad.size:
        raise MapFormatError(source, start + rec_size * int(leaf[bad[0]]),
                             "a leaf's log-odds is NaN")
    try:
        lay = _preorder.stream_layout(mask, h, max_depth=16)
    except _preorder.StreamError as err:
        raise _stream_error(source, start, rec_size, total, err) from None
    del h
    # pre-order visits leaves in code order: no sort needed
    code = lay.code[leaf]
    depth = lay.depth[leaf]
    del lay
    words = morton.split_codes(code)
    return _Leaves(words, depth, log_odds.astype(np.float32)), length, end


def _empty_leaves() -> _Leaves:
    return _Leaves(np.zeros((0, 2), np.int32), np.zeros(0, np.uint8), np.zeros(0, np.float32))


def _decode_body(buf, start, source, binary, tree_id, params, strict, claimed_size=None,
                 max_leaves=None) -> _Leaves:
    if binary:
        leaves, nodes, end = _decode_bt(buf, start, source, params, max_leaves)
    else:
        leaves, nodes, end = _decode_ot(buf, start, source, tree_id, max_leaves)
    if strict and end != buf.size:
        raise MapFormatError(source, end, f"{buf.size - end} unexpected bytes after the tree "
                             "(OctoMap ignores them; strict=False / --lenient does too)")
    if strict and claimed_size is not None and claimed_size != nodes:
        raise MapFormatError(source, None, f"size mismatch: the header claims {claimed_size} "
                             f"nodes, the data holds {nodes}")
    return leaves


def _decode_image(buf: np.ndarray, source, params, strict, allow_legacy: bool,
                  max_leaves=None):
    raw = buf[:HEADER_WINDOW].tobytes()
    if allow_legacy and not raw.startswith(BINARY_FILE_HEADER) and \
            not raw.startswith(FULL_FILE_HEADER):
        header = parse_legacy(raw, source)
    else:
        header = parse_header_prefix(lambda n: buf[:n].tobytes(), buf.size, source)
    if header.size == 0:
        # OctoMap reads no body for size 0 (an empty tree is written as a bare header).
        if strict and header.data_offset != buf.size:
            raise MapFormatError(source, header.data_offset,
                                 f"{buf.size - header.data_offset} unexpected bytes after an "
                                 "empty tree (header size 0)")
        return header, _empty_leaves()
    leaves = _decode_body(buf, header.data_offset, source, header.binary, header.tree_id,
                          params, strict, claimed_size=header.size, max_leaves=max_leaves)
    return header, leaves


def _to_map(leaves: _Leaves, resolution, params):
    """The map of sorted leaves (``from_words``: no re-sort, no uint64 copy)."""
    return _map.from_words(leaves.words, leaves.depths, leaves.log_odds, resolution,
                           params=params)


# ----------------------------------------------------------------------------- encoding


def max_likelihood_prune(codes, depths, log_odds, params=None):
    """OctoMap ``toMaxLikelihood()`` then ``prune()`` on host leaf arrays (sorted codes).

    Every leaf becomes clamping max if ``log_odds >= threshold`` else clamping min; then for
    depth 15 down to 1, each node whose 8 children are leaves of equal value collapses,
    stopping at the first depth where nothing collapses (the root is never pruned).
    Returns ``(codes, depths, log_odds)``.
    """
    p = _params_f32(params)
    occupied = np.asarray(log_odds, np.float32) >= p["occupancy_threshold_log_odds"]
    values = np.where(occupied, p["clamp_max_log_odds"], p["clamp_min_log_odds"])
    codes = np.asarray(codes, np.uint64)
    depths = np.asarray(depths).astype(np.uint8)  # a copy we modify
    removed = np.uint8(255)
    for d in range(15, 0, -1):
        idx = np.flatnonzero(depths == d + 1)
        if idx.size < 8:
            break
        block = _preorder.equal_sibling_blocks(codes[idx] & _preorder.MASKS[d], values[idx])
        if not block.size:
            break
        block = idx[block]
        depths[block[:, 0]] = d
        depths[block[:, 1:]] = removed
    keep = depths != removed
    return codes[keep], depths[keep], values[keep]


def _expand_root(codes, depths, values):
    """A depth-0 leaf -> its 8 depth-1 children (OctoMap keeps the root an inner node)."""
    if depths.size and depths[0] == 0:
        codes = np.arange(8, dtype=np.uint64) << np.uint64(45)
        return codes, np.ones(8, np.uint8), np.repeat(values[:1], 8)
    return codes, depths, values


def _host_leaves(occupancy_map):
    n = occupancy_map.num_leaves
    codes = morton.join_codes(np.asarray(occupancy_map.code)[:n])
    depths = np.asarray(occupancy_map.depth)[:n].astype(np.uint8)
    log_odds = np.asarray(occupancy_map.log_odds)[:n].astype(np.float32)
    return codes, depths, log_odds


def _encode(occupancy_map, binary: bool) -> tuple[bytes, int]:
    """(body bytes, node count) of a map."""
    if not isinstance(occupancy_map, _map.OccupancyMap):
        raise TypeError(f"expected an OccupancyMap, got {type(occupancy_map).__name__}")
    codes, depths, log_odds = _host_leaves(occupancy_map)
    _preorder.validate_leaves(codes, depths)
    if binary:
        p = _params_f32(occupancy_map.params)
        codes, depths, log_odds = _expand_root(codes, depths, log_odds)
        body, nodes = _preorder.encode_bt_pruned(
            codes, depths, log_odds, p["occupancy_threshold_log_odds"],
            p["clamp_min_log_odds"], p["clamp_max_log_odds"])
    else:
        codes, depths, log_odds = _expand_root(codes, depths, log_odds)
        body, nodes = _preorder.encode_ot(codes, depths, log_odds)
    return body.tobytes(), nodes


# ----------------------------------------------------------------------------- public API


def _format_of(path: Path) -> bool:
    """True for ``.bt``, False for ``.ot``; ``ValueError`` otherwise."""
    suffix = path.suffix.lower()
    if suffix == ".bt":
        return True
    if suffix == ".ot":
        return False
    raise ValueError(f"{path}: unknown map format {path.suffix!r}; use .bt (binary, maximum "
                     "likelihood) or .ot (full log-odds)")


def read_header(path) -> Header:
    """The header of an OctoMap file (only the header's bytes are read: 64 KiB, or more for a
    header with long comments)."""
    path = Path(path)
    is_bt = _format_of(path)
    check_input_file(path)
    with open(path, "rb") as f:
        total = os.fstat(f.fileno()).st_size
        raw = f.read(HEADER_WINDOW)
        if is_bt and not raw.startswith(BINARY_FILE_HEADER) and \
                not raw.startswith(FULL_FILE_HEADER):
            return parse_legacy(raw, path)

        def prefix(n: int) -> bytes:
            f.seek(0)
            return f.read(n)

        return parse_header_prefix(prefix, total, path)


def load(path, *, params: _map.OccupancyParams | None = None, strict: bool = True,
         max_leaves: int | None = None) -> _map.OccupancyMap:
    """Read an OctoMap ``.bt`` or ``.ot`` file into an ``OccupancyMap``.

    The extension must be ``.bt`` or ``.ot``; the format is taken from the file's first line
    (either header is accepted under either extension; a ``.bt`` without a header is tried
    as OctoMap's legacy binary layout). ``params`` (OctoMap defaults if None) sets the
    values of ``.bt`` leaves (free = clamping min, occupied = clamping max) and becomes the
    map's parameters; ``.ot`` leaves keep their stored log-odds. ``ColorOcTree`` colour and
    ``OcTreeStamped`` times are not kept (the latter are not in the file). Leaves keep
    their depth; nothing is pruned.

    Raises ``MapFormatError`` (naming the path and byte offset) for bad data; see the
    module docstring. ``strict=False`` tolerates trailing bytes and a wrong header size.

    Size: a tree of more than ``max_leaves`` leaves (default ``DEFAULT_MAX_LEAVES``, 10^8)
    raises ``MapTooLargeError``, and one whose reading would take more host memory than the
    budget (``budget.check_allocation``; about 29 B per leaf plus the map's padded 16 B
    per leaf and 96 B per node) raises ``MemoryBudgetError``, both before allocating.
    ``FileNotFoundError`` / ``IsADirectoryError`` / ``PermissionError`` name the path.
    """
    path = Path(path)
    is_bt = _format_of(path)
    check_input_file(path)
    buf = np.fromfile(path, dtype=np.uint8)
    header, leaves = _decode_image(buf, path, params, strict, allow_legacy=is_bt,
                                   max_leaves=max_leaves)
    return _to_map(leaves, header.resolution, params)


def save(occupancy_map: _map.OccupancyMap, path) -> None:
    """Write a map as ``.bt`` or ``.ot`` (by extension), byte-identical to OctoMap 1.10's
    ``writeBinary`` / ``write`` of the same tree, atomically (temp file + rename).

    ``.bt`` stores maximum likelihood only: leaves become free or occupied by the map's
    occupancy threshold, then OctoMap's prune rule applies. ``.ot`` stores every leaf's
    log-odds and inner nodes as the max of their children.
    """
    path = Path(path)
    binary = _format_of(path)
    data = to_bytes(occupancy_map, binary=binary, header=True)
    with atomic_output(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)


def to_bytes(occupancy_map: _map.OccupancyMap, binary: bool = True, *,
             header: bool = False) -> bytes:
    """Serialise a map as an ``octomap_msgs/Octomap`` payload (``header=False``, the
    message's ``data`` field) or as a whole file image (``header=True``).

    ``binary=True``: the ``.bt`` body after maximum likelihood + OctoMap's prune
    (``binaryMapToMsg`` of a tree after ``toMaxLikelihood(); prune()``); ``binary=False``:
    the ``.ot`` body (``fullMapToMsg``). The message's other fields are ``binary``,
    ``id="OcTree"`` and ``resolution=map.resolution`` (see ``to_message_fields``). An
    empty map gives an empty payload.
    """
    body, nodes = _encode(occupancy_map, bool(binary))
    if not header:
        return body
    return header_bytes(bool(binary), "OcTree", nodes, occupancy_map.resolution) + body


def from_bytes(data, binary: bool | None = None, resolution: float | None = None,
               id: str = "OcTree", *, params: _map.OccupancyParams | None = None,
               strict: bool = True, source: str = BYTES_SOURCE,
               max_leaves: int | None = None) -> _map.OccupancyMap:
    """Read a map from an ``octomap_msgs/Octomap`` payload or a whole file image.

    Args:
      data: bytes-like, ``array('b')``, an int8/uint8 array, or a list of ints (a ROS
        ``int8[]`` field).
      binary: the message's ``binary`` field (``.bt`` body if True, ``.ot`` body if False).
        Not needed for a file image (data starting with an OctoMap header line).
      resolution: the message's ``resolution`` [m]; required for a payload.
      id: the message's ``id``; selects the ``.ot`` node layout (``OcTree``,
        ``OcTreeStamped``, ``ColorOcTree``); ignored for binary data, like OctoMap.
      params: occupancy parameters (``.bt`` leaf values); OctoMap defaults if None.
      strict: refuse bytes after the tree (and, for an image, a wrong header size).
      source: the name used in error messages.
      max_leaves: refuse trees of more leaves (``MapTooLargeError``); see ``load``.

    An empty payload is an empty map (OctoMap writes no body for an empty tree). For a
    file image, ``binary``/``resolution`` must be None or agree with its header.
    """
    buf = _as_uint8(data)
    head = buf[: len(BINARY_FILE_HEADER)].tobytes()
    if head.startswith(BINARY_FILE_HEADER) or head.startswith(FULL_FILE_HEADER):
        header, leaves = _decode_image(buf, source, params, strict, allow_legacy=False,
                                       max_leaves=max_leaves)
        if binary is not None and bool(binary) != header.binary:
            raise ValueError(f"binary={binary!r} but the data is a "
                             f"{'binary (.bt)' if header.binary else 'full (.ot)'} file image")
        if resolution is not None and _check_resolution(resolution) != header.resolution:
            raise ValueError(f"resolution={resolution!r} but the file header says "
                             f"{header.resolution!r}")
        return _to_map(leaves, header.resolution, params)
    if binary is None:
        raise ValueError("binary must be given for a message payload (data without an "
                         "OctoMap header): True for .bt data, False for .ot data")
    if resolution is None:
        raise ValueError("resolution must be given for a message payload (data without an "
                         "OctoMap header)")
    res = _check_resolution(resolution)
    if not MIN_RESOLUTION <= res <= MAX_RESOLUTION:
        raise ValueError(f"resolution {res!r} is outside the supported {MIN_RESOLUTION:g}.."
                         f"{MAX_RESOLUTION:g} m")
    if buf.size == 0:
        return _map.empty(res, params=params)
    if id == "1":
        id = "OcTree"
    leaves = _decode_body(buf, 0, source, bool(binary), str(id), params, strict,
                          max_leaves=max_leaves)
    return _to_map(leaves, res, params)


def from_message(msg, *, params: _map.OccupancyParams | None = None,
                 strict: bool = True, max_leaves: int | None = None) -> _map.OccupancyMap:
    """Read an ``octomap_msgs/Octomap`` message (any object with ``binary``, ``id``,
    ``resolution`` and ``data`` attributes, e.g. from rclpy or rospy)."""
    return from_bytes(msg.data, binary=bool(msg.binary), resolution=float(msg.resolution),
                      id=str(msg.id), params=params, strict=strict, source="<message>",
                      max_leaves=max_leaves)


def to_message_fields(occupancy_map: _map.OccupancyMap, binary: bool = True) -> dict:
    """Fields of an ``octomap_msgs/Octomap`` message for a map (fill in ``header``
    yourself): ``{"binary", "id", "resolution", "data"}``, ``data`` an ``array('b')`` as
    rclpy's ``int8[]`` accepts, e.g. ``Octomap(header=h, **to_message_fields(m))``."""
    payload = to_bytes(occupancy_map, binary=binary)
    return {"binary": bool(binary), "id": "OcTree",
            "resolution": float(occupancy_map.resolution),
            "data": array.array("b", payload)}


