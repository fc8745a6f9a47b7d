"""OctoMap file headers (``AbstractOcTree::readHeader`` / ``writeHeader``) and the old
headerless ``.bt`` layout.

Header (both formats; ``\\n`` line ends)::

    # Octomap OcTree binary file        (.bt)   /   # Octomap OcTree file   (.ot)
    # (feel free to add / change comments, but leave the first line as it is!)
    #
    id OcTree
    size <nodes>                         OctoMap size(): every node, inner and root included
    res <resolution>                     C++ ostream default = printf "%g"
    data

Read like ``readHeader``: whitespace-separated tokens of any length, ``#`` comments and
unknown keywords skip to the end of the line, ``id`` / ``size`` / ``res`` values read as
``std::istream >>`` reads them, ``data`` ends the header after its line. Errors are
``MapFormatError`` naming the source and byte offset.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from .errors import MapFormatError

__all__ = ["BINARY_FILE_HEADER", "FULL_FILE_HEADER", "HEADER_WINDOW", "MAX_RESOLUTION",
           "MIN_RESOLUTION", "Header", "check_header_resolution", "format_resolution",
           "header_bytes", "parse_header", "parse_header_prefix", "parse_legacy"]

BINARY_FILE_HEADER = b"# Octomap OcTree binary file"
FULL_FILE_HEADER = b"# Octomap OcTree file"
_COMMENT = b"# (feel free to add / change comments, but leave the first line as it is!)\n#\n"

_WS = b" \t\n\r\v\f"
_TOKEN_RE = re.compile(rb"[^ \t\n\r\v\f]*")
#: What ``std::istream >> double`` / ``>> unsigned`` consume (libstdc++ ``num_get``): an
#: optional sign, digits with one optional point, an optional exponent. The rest of the
#: token is left in the stream (``res 1_0`` reads 1, then ``_0`` is the next token).
_DOUBLE_RE = re.compile(rb"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_UNSIGNED_RE = re.compile(rb"\+?[0-9]+")
#: First read of a file's header; a longer header (long comments) is read in doubling steps.
HEADER_WINDOW = 1 << 16
#: Resolutions [m] a map may have: OctoMap accepts any positive double, but beyond these the
#: float32 voxel geometry under- or overflows (docs/design.md, "Resolution range").
MIN_RESOLUTION = 1e-6
MAX_RESOLUTION = 1e6


@dataclass(frozen=True)
class Header:
    """A parsed OctoMap file header.

    ``binary`` (``.bt``) or full (``.ot``); ``tree_id`` as written (``"1"`` -> ``"OcTree"``);
    ``size`` the claimed node count; ``resolution`` metres; ``data_offset`` the first body
    byte; ``legacy`` for the old headerless ``.bt`` layout.
    """

    binary: bool
    tree_id: str
    size: int
    resolution: float
    data_offset: int
    legacy: bool = False



def format_resolution(resolution: float) -> str:
    """``res`` as C++ ``ostream << double`` prints it (``%g``: 6 significant digits)."""
    return f"{float(resolution):g}"


def header_bytes(binary: bool, tree_id: str, size: int, resolution: float) -> bytes:
    first = BINARY_FILE_HEADER if binary else FULL_FILE_HEADER
    tail = f"id {tree_id}\nsize {int(size)}\nres {format_resolution(resolution)}\ndata\n"
    return first + b"\n" + _COMMENT + tail.encode("ascii")



class _HeaderCut(Exception):
    """The header runs past the end of the bytes parsed so far (read more and retry)."""


def _skip_ws(buf: bytes, pos: int) -> int:
    n = len(buf)
    while pos < n and buf[pos] in _WS:
        pos += 1
    return pos


def _token(buf: bytes, pos: int, complete: bool) -> tuple[bytes, int, int]:
    """Next whitespace-delimited token (``std::istream >> std::string``): (token, start, end).
    Empty at the end of the data; ``_HeaderCut`` where more data may follow."""
    start = _skip_ws(buf, pos)
    end = _TOKEN_RE.match(buf, start).end()
    if end == len(buf) and not complete:
        raise _HeaderCut
    return buf[start:end], start, end


def _number(buf: bytes, pos: int, complete: bool, pattern) -> tuple[bytes, int, int]:
    """What ``std::istream >> number`` consumes after ``pos``: (text, start, end); the text is
    empty where the stream would fail (no number there)."""
    start = _skip_ws(buf, pos)
    m = pattern.match(buf, start)
    end = m.end() if m else start
    if end == len(buf) and not complete:
        raise _HeaderCut
    return buf[start:end], start, end


def _skip_line(buf: bytes, pos: int, complete: bool) -> int:
    nl = buf.find(b"\n", pos)
    if nl < 0 and not complete:
        raise _HeaderCut
    return len(buf) if nl < 0 else nl + 1


def check_header_resolution(res: float, source, offset: int) -> None:
    if not (MIN_RESOLUTION <= res <= MAX_RESOLUTION):
        raise MapFormatError(source, offset, f"header res {res!r} is outside the supported "
                             f"{MIN_RESOLUTION:g}..{MAX_RESOLUTION:g} m")


def parse_header(buf: bytes, source, complete: bool = True) -> Header:
    """Parse a file image's header (``AbstractOcTree::readHeader`` semantics: tokens of any
    length, numbers read as ``std::istream`` does). With ``complete=False`` ``buf`` is a
    prefix of the file and ``_HeaderCut`` asks for more of it."""
    if buf.startswith(BINARY_FILE_HEADER):
        binary = True
    elif buf.startswith(FULL_FILE_HEADER):
        binary = False
    elif not complete and len(buf) < len(BINARY_FILE_HEADER):
        raise _HeaderCut
    else:
        raise MapFormatError(source, 0, "not an OctoMap file: the first line must start with "
                             f"{BINARY_FILE_HEADER.decode()!r} or {FULL_FILE_HEADER.decode()!r}")
    pos = _skip_line(buf, 0, complete)
    tree_id, size, res = None, 0, 0.0
    while True:
        tok, start, pos = _token(buf, pos, complete)
        if not tok:
            raise MapFormatError(source, start, "header ends without a 'data' line "
                                 "(truncated or not an OctoMap file)")
        if tok == b"data":
            pos = _skip_line(buf, pos, complete)
            break
        if tok.startswith(b"#"):
            pos = _skip_line(buf, pos, complete)
        elif tok == b"id":
            val, vstart, pos = _token(buf, pos, complete)
            if not val:
                raise MapFormatError(source, vstart, "header 'id' has no value")
            try:
                tree_id = val.decode("ascii")
            except UnicodeDecodeError:
                raise MapFormatError(source, vstart, "header id is not ASCII") from None
        elif tok == b"size":
            val, vstart, pos = _number(buf, pos, complete, _UNSIGNED_RE)
            if not val or int(val) > 0xFFFFFFFF:  # OctoMap reads an unsigned
                raise MapFormatError(source, vstart, f"header size {buf[vstart:vstart + 40]!r}"
                                     " is not a node count")
            size = int(val)
        elif tok == b"res":
            val, vstart, pos = _number(buf, pos, complete, _DOUBLE_RE)
            if not val:
                raise MapFormatError(source, vstart, f"header res {buf[vstart:vstart + 40]!r} "
                                     "is not a number")
            res = float(val)
            if not res > 0:
                raise MapFormatError(source, vstart, f"header res {res!r} must be a "
                                     "positive resolution in metres")
            check_header_resolution(res, source, vstart)
        else:  # unknown keyword: OctoMap warns and skips the line
            pos = _skip_line(buf, pos, complete)
    if not tree_id:
        raise MapFormatError(source, pos, "header has no 'id'")
    if res <= 0:
        raise MapFormatError(source, pos, "header has no positive 'res'")
    if tree_id == "1":  # deprecated id, rewritten by OctoMap
        tree_id = "OcTree"
    return Header(binary, tree_id, size, res, pos)


def parse_header_prefix(read_prefix, total: int, source) -> Header:
    """Parse a header from ``read_prefix(n)`` (the first ``n`` bytes of ``total``), reading
    64 KiB first and doubling while the header runs on."""
    n = HEADER_WINDOW
    while True:
        complete = n >= total
        try:
            return parse_header(read_prefix(n), source, complete)
        except _HeaderCut:
            n *= 2


def parse_legacy(buf: bytes, source) -> Header:
    """Old headerless ``.bt``: int32 tree type 3, float64 resolution, uint32 size."""
    if len(buf) < 16 or int(np.frombuffer(buf, "<i4", 1, 0)[0]) != 3:
        raise MapFormatError(source, 0, "not an OctoMap binary file: the first line does not "
                             f"start with {BINARY_FILE_HEADER.decode()!r} and it is no legacy "
                             "binary OcTree (type 3)")
    res = float(np.frombuffer(buf, "<f8", 1, 4)[0])
    if not (math.isfinite(res) and res > 0):
        raise MapFormatError(source, 4, f"legacy header resolution {res!r} is not positive")
    check_header_resolution(res, source, 4)
    size = int(np.frombuffer(buf, "<u4", 1, 12)[0])
    return Header(True, "OcTree", size, res, 16, legacy=True)


