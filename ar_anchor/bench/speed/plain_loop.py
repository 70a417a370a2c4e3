"""The plain OpenCV loop as a process of its own, for ``ar-anchor bench run``'s alternating runs.

Run as a script (``python plain_loop.py VIDEO CAMERA_YML DICTIONARY MARKER_LENGTH_M``), not imported: it
imports only OpenCV, PyAV and NumPy, as a newcomer's script would, so its process start-up is Python's
and those libraries' alone. It decodes every frame with PyAV (``thread_type = "AUTO"``, BGR frames: as
``ar-anchor replay`` decodes), converts it to grey, runs ``ArucoDetector.detectMarkers`` with default
``DetectorParameters`` and ``solvePnPGeneric(SOLVEPNP_IPPE_SQUARE)`` per marker, and writes nothing but
one JSON line on stdout: frames, markers found, and its own wall time from before the video opened.
"""

from __future__ import annotations

import json
import sys
import time

__all__ = ["main"]


def main(argv: list[str]) -> int:
    """Run the loop over ``argv = [video, camera_yml, dictionary, marker_length_m]``; print one JSON line."""
    import av
    import cv2
    import numpy as np

    video, camera_yml, dictionary, length = argv[0], argv[1], argv[2], float(argv[3])
    storage = cv2.FileStorage(camera_yml, cv2.FILE_STORAGE_READ)
    k = storage.getNode("camera_matrix").mat()
    dist = storage.getNode("distortion_coefficients").mat()
    storage.release()
    detector = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), cv2.aruco.DetectorParameters()
    )
    h = length / 2.0
    square = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]], np.float32)
    start = time.perf_counter()
    frames = markers = 0
    with av.open(video) as container:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        for frame in container.decode(stream):
            image = frame.to_ndarray(format="bgr24")
            grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            corners, ids, _ = detector.detectMarkers(grey)
            for marker_corners in corners:
                count, _, _, _ = cv2.solvePnPGeneric(
                    square, marker_corners.reshape(4, 2), k, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE
                )
                markers += int(count > 0)
            frames += 1
    wall = time.perf_counter() - start
    print(json.dumps({"frames": frames, "markers": markers, "loop_wall_s": wall}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
