"""The MCAP export: a ROS 2 bag in one file (``ros2`` profile, CDR messages), written with ``mcap`` and
``mcap-ros2-support`` (no ROS install needed to write it).

Topics (every message's log time and header stamp: the frame's timestamp, as in ``poses.csv``):

- ``/tf`` (``tf2_msgs/msg/TFMessage``): per frame with a pose, one ``TransformStamped`` per target that
  has a row in ``poses.csv`` that frame (any state); ``header.frame_id`` the camera's optical frame
  (``camera``: x right, y down, z forward, OpenCV's and ROS's optical-frame convention),
  ``child_frame_id`` the target's frame name (:func:`~.tables.frame_name`), the transform
  ``camera_from_target`` (tf's parent-from-child).
- ``/camera/camera_info`` (``sensor_msgs/msg/CameraInfo``): per frame with a pose, or per image when images
  are exported: K, D (``plumb_bob``: k1 k2 p1 p2 k3; ``rational_polynomial`` for 8 coefficients), R = I,
  P = [K | 0], the calibrated size.
- ``/camera/image/compressed`` (``sensor_msgs/msg/CompressedImage``, JPEG): only when images are exported.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ...camera import CameraModel
from ...errors import InputError, OutputError, printable
from .poses import PoseRow
from .ros2_msgs import CAMERA_INFO, COMPRESSED_IMAGE, TF_MESSAGE
from .tables import FrameNames

__all__ = ["CAMERA_FRAME", "TOPICS", "McapExportWriter", "ros_distortion"]

CAMERA_FRAME = "camera"
TOPICS = {"tf": "/tf", "camera_info": "/camera/camera_info", "image": "/camera/image/compressed"}
JPEG_QUALITY = 90


def ros_distortion(camera: CameraModel) -> tuple[str, list[float]]:
    """CameraInfo's ``distortion_model`` and ``d`` for ``camera``'s OpenCV coefficients: ``plumb_bob`` (k1 k2 p1
    p2 k3) for none, 4 or 5; ``rational_polynomial`` (k1 k2 p1 p2 k3 k4 k5 k6) for 8. 12 or 14 (thin prism,
    tilted sensor) have no ROS model: refused unless the extra ones are zero."""
    d = [float(v) for v in camera.dist_coeffs]
    if len(d) > 8 and not any(d[8:]):
        d = d[:8]
    if len(d) == 8 and not any(d[5:]):
        d = d[:5]
    if len(d) <= 5:
        return "plumb_bob", d + [0.0] * (5 - len(d))
    if len(d) == 8:
        return "rational_polynomial", d
    raise InputError(
        f"the camera's {len(d)} distortion coefficients (thin prism or tilted model) have no ROS CameraInfo model "
        "(plumb_bob: 5, rational_polynomial: 8)"
    )


def _stamp(timestamp_ns: int) -> dict[str, int]:
    seconds, nanoseconds = divmod(int(timestamp_ns), 1_000_000_000)
    return {"sec": seconds, "nanosec": nanoseconds}


class McapExportWriter:
    """Writes the bag (see the module doc) to ``path``; :meth:`close` finishes the file (its index and footer)."""

    def __init__(self, path: Path, camera: CameraModel, names: FrameNames, *, camera_frame: str = CAMERA_FRAME) -> None:
        from mcap.writer import CompressionType  # noqa: PLC0415 - only exports need mcap
        from mcap_ros2.writer import Writer  # noqa: PLC0415

        self.path = path
        self.camera = camera
        self._names = names
        self._frame = camera_frame
        self._distortion = ros_distortion(camera)
        try:
            self._file = open(path, "wb")  # noqa: SIM115 - closed in close()
        except OSError as err:
            raise OutputError(f"{printable(path)}: cannot write ({err.strerror or err})") from None
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._schemas = {
            key: self._writer.register_msgdef(*definition)
            for key, definition in (("tf", TF_MESSAGE), ("camera_info", CAMERA_INFO), ("image", COMPRESSED_IMAGE))
        }
        self.messages = {key: 0 for key in TOPICS}
        self._last_info_ns: int | None = None

    def _write(self, key: str, message: dict[str, Any], timestamp_ns: int) -> None:
        if timestamp_ns < 0:
            raise OutputError(f"{printable(self.path)}: timestamp {timestamp_ns} ns is before 1970: no MCAP log time")
        try:
            self._writer.write_message(
                TOPICS[key], self._schemas[key], message, log_time=timestamp_ns, publish_time=timestamp_ns
            )
        except OSError as err:
            raise OutputError(f"{printable(self.path)}: cannot write ({err.strerror or err})") from None
        self.messages[key] += 1

    def _header(self, timestamp_ns: int) -> dict[str, Any]:
        return {"stamp": _stamp(timestamp_ns), "frame_id": self._frame}

    def write_poses(self, rows: list[PoseRow]) -> None:
        """One frame's ``/tf`` message (and its camera info, unless images bring their own)."""
        timestamp_ns = rows[0].timestamp_ns
        transforms = []
        for row in rows:
            x, y, z, w = row.quaternion
            tx, ty, tz = (float(v) for v in row.pose.tvec)
            transforms.append(
                {
                    "header": self._header(timestamp_ns),
                    "child_frame_id": self._names(row.target),
                    "transform": {
                        "translation": {"x": tx, "y": ty, "z": tz},
                        "rotation": {"x": float(x), "y": float(y), "z": float(z), "w": float(w)},
                    },
                }
            )
        self._write("tf", {"transforms": transforms}, timestamp_ns)

    def write_camera_info(self, timestamp_ns: int) -> None:
        """``/camera/camera_info`` at ``timestamp_ns`` (once per timestamp)."""
        if self._last_info_ns == timestamp_ns:
            return
        self._last_info_ns = timestamp_ns
        k = np.asarray(self.camera.camera_matrix, dtype=np.float64)
        p = np.zeros((3, 4))
        p[:, :3] = k
        model, d = self._distortion
        message = {
            "header": self._header(timestamp_ns),
            "height": self.camera.height,
            "width": self.camera.width,
            "distortion_model": model,
            "d": d,
            "k": [float(v) for v in k.reshape(-1)],
            "r": [float(v) for v in np.eye(3).reshape(-1)],
            "p": [float(v) for v in p.reshape(-1)],
            "binning_x": 0,
            "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
        }
        self._write("camera_info", message, timestamp_ns)

    def write_image(self, image: np.ndarray, timestamp_ns: int) -> None:
        """``image`` (BGR) as a JPEG ``CompressedImage`` at ``timestamp_ns``."""
        import cv2  # noqa: PLC0415

        ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise OutputError(f"{printable(self.path)}: cannot encode the image of {timestamp_ns} ns as JPEG")
        message = {"header": self._header(timestamp_ns), "format": "jpeg", "data": data.tobytes()}
        self._write("image", message, timestamp_ns)

    def close(self) -> None:
        """Finish the file (summary, index, footer) and close it."""
        try:
            self._writer.finish()
        except OSError as err:
            raise OutputError(f"{printable(self.path)}: cannot write ({err.strerror or err})") from None
        finally:
            self._file.close()

    def abandon(self) -> None:
        """Close the file without finishing it (the export failed: it is removed)."""
        self._file.close()
