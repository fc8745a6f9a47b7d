"""Maps in ROS bags: ``octomap_msgs/Octomap`` messages (binary ``.bt`` or full ``.ot`` payloads)
read from and written to ROS 1 ``.bag`` files and ROS 2 bags (sqlite3 or MCAP) with ``rosbags``.

Payloads are decoded by ``io.octree_format.from_bytes`` and encoded by ``to_bytes``, the code that
reads and writes ``.bt`` / ``.ot`` files, so a map read from a bag has the same leaves, bit for bit,
as the file OctoMap would have written for it. Message fields follow octomap_msgs'
``binaryMapToMsg`` / ``fullMapToMsg``: ``id`` is the tree type (``"OcTree"``), ``binary`` says
which payload, ``resolution`` in metres.
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Iterator, NamedTuple

import numpy as np

from ...map import OccupancyMap, OccupancyParams
from ..octree_format import from_bytes, to_bytes
from ._store import OCTOMAP_TYPE, BagError, connections_of, open_reader, stamp_ns, typestore

__all__ = ["BagMap", "read_bag", "select_map", "write_bag", "DEFAULT_MAP_TOPICS"]

#: octomap_server's topics for binary and full maps
DEFAULT_MAP_TOPICS = {True: "/octomap_binary", False: "/octomap_full"}


class BagMap(NamedTuple):
    """One map read from a bag.

    Fields:
      map: the decoded ``OccupancyMap``.
      stamp_ns: int, the message's header stamp [ns since the epoch] (the bag's record time if
        the stamp is 0).
      frame_id: str, the header's frame (the map's frame).
      topic: str, the topic it came from.
      binary: bool, whether the payload was binary (``.bt``-like, maximum likelihood).
      tree_id: str, the message's ``id`` (``"OcTree"``, ``"OcTreeStamped"``, ``"ColorOcTree"``).
      payload_bytes: int, the size of the message's ``data`` [bytes].
    """

    map: OccupancyMap
    stamp_ns: int
    frame_id: str
    topic: str
    binary: bool
    tree_id: str
    payload_bytes: int


class _Raw(NamedTuple):
    msg: object      # the deserialised octomap_msgs/Octomap
    stamp_ns: int    # header stamp [ns]
    topic: str


def _raw_maps(path, topic: str | None) -> Iterator[_Raw]:
    with contextlib.closing(open_reader(path)) as reader:
        conns = connections_of(reader, path, topic, (OCTOMAP_TYPE,), "octomap_msgs/Octomap")
        for con, t, raw in reader.messages(connections=conns):
            try:
                msg = reader.deserialize(raw, con.msgtype)
            except Exception as err:  # rosbags' decoder errors
                raise BagError(f"{path}: {con.topic}: message at bag time {t / 1e9:.9f} s does not decode "
                               f"as octomap_msgs/Octomap ({' '.join(str(err).split())[:160]})") from None
            yield _Raw(msg, stamp_ns(msg.header, t), con.topic)


def _decode(path, r: _Raw, params, strict) -> BagMap:
    msg = r.msg
    source = f"{path} {r.topic} @ {r.stamp_ns / 1e9:.9f} s"
    m = from_bytes(msg.data, binary=bool(msg.binary), resolution=float(msg.resolution), id=str(msg.id),
                   params=params, strict=strict, source=source)
    return BagMap(m, r.stamp_ns, str(msg.header.frame_id), r.topic, bool(msg.binary), str(msg.id), len(msg.data))


def read_bag(path, topic: str | None = None, *, params: OccupancyParams | None = None,
             strict: bool = True) -> Iterator[BagMap]:
    """Yield every ``octomap_msgs/Octomap`` map of a bag, in bag order.

    Args:
      path: a ROS 1 ``.bag`` file, a ROS 2 bag folder, or its ``.db3`` / ``.mcap`` file.
      topic: the topic to read; ``None`` reads the bag's one Octomap topic.
      params: occupancy parameters for binary payloads (OctoMap defaults if None).
      strict: refuse payload bytes after the tree.

    Yields ``BagMap`` (map, stamp, frame, topic, binary, tree id).

    Raises:
      FileNotFoundError: no such path.
      BagError (a ``ValueError``): unreadable bag, missing topic, several Octomap topics and no
        ``topic``, a topic of another type, a message that does not decode.
      MapFormatError (a ``ValueError``): a payload that is not an octree, named by bag, topic, stamp.
    """
    for r in _raw_maps(path, topic):
        yield _decode(path, r, params, strict)


def select_map(path, topic: str | None = None, stamp: float | None = None, *,
               params: OccupancyParams | None = None, strict: bool = True) -> BagMap:
    """The map of ``topic`` as it was at time ``stamp``: the message with the latest header
    stamp at or before ``stamp`` [s since the epoch]; the latest of all for ``None``. Only that
    message's payload is decoded.

    Raises ``BagError`` for an empty topic, a non-finite ``stamp`` or one before the first map
    (naming the topic's first and last stamps), besides what ``read_bag`` raises."""
    if stamp is not None and not math.isfinite(stamp):
        raise BagError(f"{path}: --stamp {stamp} is not a finite time in seconds")
    limit = None if stamp is None else int(round(stamp * 1e9))
    best, first, last, n, seen = None, None, None, 0, topic
    for r in _raw_maps(path, topic):
        n, seen = n + 1, r.topic
        first = r.stamp_ns if first is None else min(first, r.stamp_ns)
        last = r.stamp_ns if last is None else max(last, r.stamp_ns)
        if (limit is None or r.stamp_ns <= limit) and (best is None or r.stamp_ns >= best.stamp_ns):
            best = r
    name = seen or "the Octomap topic"
    if n == 0:
        raise BagError(f"{path}: {name} has no messages")
    if best is None:
        raise BagError(f"{path}: no map on {name} at or before --stamp {stamp:.9f} s "
                       f"({n} maps from {first / 1e9:.9f} to {last / 1e9:.9f} s)")
    return _decode(path, best, params, strict)


def _bag_kind(path: Path, storage: str | None) -> tuple[int, str | None]:
    if path.suffix.lower() == ".bag":
        if storage not in (None, "ros1"):
            raise ValueError(f"{path}: a .bag is a ROS 1 bag; storage {storage!r} is for ROS 2 bags")
        return 1, None
    if path.suffix.lower() in (".db3", ".mcap"):
        raise ValueError(f"{path}: name the ROS 2 bag folder to write, not a {path.suffix} file in it")
    storage = storage or "mcap"
    if storage not in ("mcap", "sqlite3"):
        raise ValueError(f"{path}: ROS 2 bag storage must be 'mcap' or 'sqlite3', got {storage!r}")
    return 2, storage


def write_bag(path, maps, *, topic: str | None = None, frame_id: str = "map", stamps_ns=None,
              binary: bool = True, storage: str | None = None) -> None:
    """Write maps as ``octomap_msgs/Octomap`` messages, one per map, as octomap_server
    publishes them (``binaryMapToMsg`` for ``binary=True``, else ``fullMapToMsg``).

    Args:
      path: ``*.bag`` writes a ROS 1 bag; anything else a ROS 2 bag folder (rosbag2 format
        version 8) with ``storage`` ``"mcap"`` (default) or ``"sqlite3"``.
      maps: an ``OccupancyMap`` or a sequence of them.
      topic: default ``/octomap_binary`` or ``/octomap_full`` (octomap_server's names).
      frame_id: the header frame of every message.
      stamps_ns: one header stamp [ns] per map (also the record time); default: now.
      binary: binary payloads (``.bt``: maximum likelihood, pruned) or full (``.ot``: log-odds).

    The bag is written in a temporary folder next to ``path`` and renamed into place, so a
    failure never leaves half a bag; an existing ``path`` is replaced."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin, Writer as Writer2

    path = Path(path)
    maps = [maps] if isinstance(maps, OccupancyMap) else list(maps)
    stamps = [time.time_ns()] * len(maps) if stamps_ns is None else [int(s) for s in stamps_ns]
    if len(stamps) != len(maps):
        raise ValueError(f"{path}: {len(maps)} maps but {len(stamps)} stamps")
    ros, storage = _bag_kind(path, storage)
    topic = topic or DEFAULT_MAP_TOPICS[bool(binary)]
    store = typestore(ros)
    Octomap, Header = store.types[OCTOMAP_TYPE], store.types["std_msgs/msg/Header"]
    Time = store.types["builtin_interfaces/msg/Time"]
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise FileNotFoundError(f"{path}: output folder {folder} does not exist")
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=folder))
    try:
        target = tmp / path.name
        if ros == 1:
            writer = Writer1(target)
        else:
            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
            writer = Writer2(target, version=8, storage_plugin=plugin)
        with writer:
            con = writer.add_connection(topic, OCTOMAP_TYPE, typestore=store)
            for seq, (m, t) in enumerate(zip(maps, stamps)):
                stamp = Time(sec=t // 1_000_000_000, nanosec=t % 1_000_000_000)
                header = Header(seq=seq, stamp=stamp, frame_id=frame_id) if ros == 1 else \
                    Header(stamp=stamp, frame_id=frame_id)
                payload = np.frombuffer(to_bytes(m, binary=binary), np.int8)
                msg = Octomap(header=header, binary=bool(binary), id="OcTree",
                              resolution=float(m.resolution), data=payload)
                data = store.serialize_ros1(msg, OCTOMAP_TYPE) if ros == 1 else \
                    store.serialize_cdr(msg, OCTOMAP_TYPE)
                writer.write(con, t, data)
        old = None
        if path.is_dir():  # a ROS 2 bag folder being replaced: move it aside first
            old = tmp / ".old"
            os.replace(path, old)
        os.replace(target, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
