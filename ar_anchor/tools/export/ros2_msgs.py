"""The ROS 2 message definitions the MCAP export writes, as the schema text of a ROS 2 bag.

An MCAP file of the ``ros2`` profile carries each channel's message definition (schema encoding
``ros2msg``): the type's own ``.msg`` text followed by every type it uses, each after a line of 80 ``=``
and a ``MSG: <package>/<Type>`` line, the form ``ros2 bag record`` writes and
``mcap_ros2.writer.Writer.register_msgdef`` takes. The field lists below are those of ROS 2's
``common_interfaces``, ``geometry2`` and ``rcl_interfaces`` (``builtin_interfaces``) packages (Humble to
Rolling: these types have not changed), comments dropped; the tests check them field by field against
the definitions ``rosbags`` ships for ROS 2 Humble.
"""

from __future__ import annotations

__all__ = ["COMPRESSED_IMAGE", "CAMERA_INFO", "TF_MESSAGE", "msgdef"]

_SEPARATOR = "=" * 80

# each type's own fields, by full name (package/Type)
_FIELDS = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/Transform": "Vector3 translation\nQuaternion rotation\n",
    "geometry_msgs/TransformStamped": "std_msgs/Header header\nstring child_frame_id\nTransform transform\n",
    "tf2_msgs/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "sensor_msgs/RegionOfInterest": (
        "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n"
    ),
    "sensor_msgs/CameraInfo": (
        "std_msgs/Header header\n"
        "uint32 height\n"
        "uint32 width\n"
        "string distortion_model\n"
        "float64[] d\n"
        "float64[9] k\n"
        "float64[9] r\n"
        "float64[12] p\n"
        "uint32 binning_x\n"
        "uint32 binning_y\n"
        "RegionOfInterest roi\n"
    ),
    "sensor_msgs/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n",
}

# the types each type uses (directly or not), in the order they follow it
_DEPENDENCIES = {
    "tf2_msgs/TFMessage": [
        "geometry_msgs/TransformStamped",
        "std_msgs/Header",
        "builtin_interfaces/Time",
        "geometry_msgs/Transform",
        "geometry_msgs/Vector3",
        "geometry_msgs/Quaternion",
    ],
    "sensor_msgs/CameraInfo": ["std_msgs/Header", "builtin_interfaces/Time", "sensor_msgs/RegionOfInterest"],
    "sensor_msgs/CompressedImage": ["std_msgs/Header", "builtin_interfaces/Time"],
}


def msgdef(name: str) -> str:
    """The schema text of ``name`` (``package/Type``): its fields, then each type it uses after a separator."""
    parts = [_FIELDS[name]]
    for dependency in _DEPENDENCIES.get(name, []):
        parts.append(f"{_SEPARATOR}\nMSG: {dependency}\n{_FIELDS[dependency]}")
    return "\n".join(parts)


# (schema name as rosbag2 records it, schema text)
TF_MESSAGE = ("tf2_msgs/msg/TFMessage", msgdef("tf2_msgs/TFMessage"))
CAMERA_INFO = ("sensor_msgs/msg/CameraInfo", msgdef("sensor_msgs/CameraInfo"))
COMPRESSED_IMAGE = ("sensor_msgs/msg/CompressedImage", msgdef("sensor_msgs/CompressedImage"))
