"""Opening ROS 1 / ROS 2 bags with ``rosbags``: type stores that know ``octomap_msgs/Octomap``,
the one error type, and message iteration by topic.

``rosbags`` is an optional dependency (the ``bags`` extra); it is imported when a bag is opened.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["BagError", "OCTOMAP_TYPE", "OCTOMAP_MSG", "TFMESSAGE_MSG", "is_bag", "bag_root", "typestore",
           "open_reader", "connections_of", "stamp_ns"]

#: the type name rosbags uses for ``octomap_msgs/Octomap`` (ROS 1 and ROS 2 alike)
OCTOMAP_TYPE = "octomap_msgs/msg/Octomap"
#: ``octomap_msgs/msg/Octomap.msg`` without comments (same fields in ROS 1 and ROS 2; ROS 1's
#: md5sum of this definition is ``9a45536b45c5e409cd49f04bb2d9999f``, as rosmsg reports)
OCTOMAP_MSG = """std_msgs/Header header
bool binary
string id
float64 resolution
int8[] data
"""
#: ``tf2_msgs/TFMessage.msg`` (missing from rosbags' ROS 1 store)
TFMESSAGE_MSG = "geometry_msgs/TransformStamped[] transforms\n"
_ROS2_FILES = (".db3", ".mcap")


class BagError(ValueError):
    """A bag that cannot be read, a topic it lacks, a message that is not what was asked for.
    The message names the bag (and the topic / stamp) on one line."""


def is_bag(path) -> bool:
    """Whether ``path`` names a bag: a ROS 1 ``.bag`` file, a ROS 2 bag folder (with a
    ``metadata.yaml``) or one of its ``.db3`` / ``.mcap`` files."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".bag" or suffix in _ROS2_FILES:
        return True
    return path.is_dir() and (path / "metadata.yaml").is_file()


def bag_root(path) -> Path:
    """The path rosbags opens: a ``.db3`` / ``.mcap`` file inside a bag folder becomes the
    folder (its ``metadata.yaml`` lists the files); anything else is returned as is."""
    path = Path(path)
    if path.suffix.lower() in _ROS2_FILES and (path.parent / "metadata.yaml").is_file():
        return path.parent
    return path


def typestore(ros_version: int):
    """A rosbags ``Typestore`` with the common messages of ROS 1 Noetic (``ros_version=1``) or
    ROS 2 Jazzy (``2``) plus ``octomap_msgs/Octomap`` and ``tf2_msgs/TFMessage``."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros_version == 1 else Stores.ROS2_JAZZY)
    extra = get_types_from_msg(OCTOMAP_MSG, OCTOMAP_TYPE)
    if "tf2_msgs/msg/TFMessage" not in store.types:
        extra.update(get_types_from_msg(TFMESSAGE_MSG, "tf2_msgs/msg/TFMessage"))
    store.register(extra)
    return store


def open_reader(path):
    """An opened rosbags ``AnyReader`` for the bag at ``path`` (use as a context manager).
    Bags without embedded definitions (ROS 2 before Iron) decode with ``typestore(2)``.

    Raises ``FileNotFoundError`` for a missing path, ``BagError`` for one rosbags cannot read,
    ``ModuleNotFoundError`` naming the ``bags`` extra when rosbags is not installed."""
    try:
        from rosbags.highlevel import AnyReader
    except ModuleNotFoundError as err:
        raise ModuleNotFoundError(f"reading ROS bags needs rosbags: pip install 'octomerge_jax[bags]' "
                                  f"({err})", name=err.name) from None
    root = bag_root(path)
    if not root.exists():
        raise FileNotFoundError(f"{path}: no such bag")
    try:
        reader = AnyReader([root], default_typestore=typestore(2))
        reader.open()
    except FileNotFoundError:
        raise
    except Exception as err:  # rosbags raises reader, yaml, sqlite and decoder errors
        raise BagError(f"{path}: not a readable ROS bag ({_one_line(err)})") from None
    return reader


def connections_of(reader, path, topic: str | None, msgtypes: tuple[str, ...], what: str):
    """The reader's connections on ``topic`` (or, for ``None``, every connection of one of
    ``msgtypes``), checked: the topic exists and carries one of ``msgtypes``.

    Raises ``BagError`` naming the topics the bag does have."""
    def listing():
        return ", ".join(f"{c.topic} ({c.msgtype.replace('/msg/', '/')})" for c in reader.connections) or "none"

    if topic is None:
        conns = [c for c in reader.connections if c.msgtype in msgtypes]
        if not conns:
            raise BagError(f"{path}: no {what} topic in the bag (topics: {listing()})")
        topics = sorted({c.topic for c in conns})
        if len(topics) > 1:
            raise BagError(f"{path}: several {what} topics ({', '.join(topics)}); choose one with --topic")
        return conns
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        raise BagError(f"{path}: no topic {topic} in the bag (topics: {listing()})")
    bad = [c.msgtype for c in conns if c.msgtype not in msgtypes]
    if bad:
        want = " or ".join(t.replace("/msg/", "/") for t in msgtypes)
        raise BagError(f"{path}: topic {topic} carries {bad[0].replace('/msg/', '/')}, not {want}")
    return conns


def stamp_ns(header, bag_time_ns: int) -> int:
    """A message's time [ns]: its header stamp, or the bag's record time when the stamp is 0."""
    t = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    return t if t > 0 else int(bag_time_ns)


def _one_line(err) -> str:
    text = " ".join(str(err).split())
    return text if len(text) < 200 else text[:197] + "..."
