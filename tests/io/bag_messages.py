"""Shared helpers of the tests that write ROS bags by hand: the type store of a ROS
version and a message header."""

from __future__ import annotations

from rosbags.typesys import Stores, get_typestore


def store_for(version: int):
    """The rosbags type store of ROS 1 (noetic) or ROS 2 (humble)."""
    return get_typestore(Stores.ROS1_NOETIC if version == 1 else Stores.ROS2_HUMBLE)


def header_msg(store, stamp_ns: int, frame: str):
    """A ``std_msgs/Header`` stamped ``stamp_ns`` (ns) in ``frame`` (with ``seq`` on ROS 1)."""
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    time = store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
    header = store.types["std_msgs/msg/Header"]
    if "seq" in header.__dataclass_fields__:
        return header(seq=0, stamp=time, frame_id=frame)
    return header(stamp=time, frame_id=frame)
