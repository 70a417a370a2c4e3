"""The plain OpenCV loop as a process of its own, for the alternating runs of ``ar-anchor bench run`` and
``ar-anchor bench speed``.

Run as a script (``python plain_loop.py VIDEO CAMERA_YML DICTIONARY MARKER_LENGTH_M [--subpix] [--ids]``), not
imported: it imports only OpenCV, PyAV and NumPy, as a newcomer's script would, so its process start-up is
Python's and those libraries' alone. It decodes every frame with PyAV (``thread_type = "AUTO"``, BGR frames:
as ``ar-anchor replay`` decodes), converts it to grey, runs ``ArucoDetector.detectMarkers`` (default
``DetectorParameters``; ``--subpix``: with ``cornerRefinementMethod = CORNER_REFINE_SUBPIX``) and
``solvePnPGeneric(SOLVEPNP_IPPE_SQUARE)`` per marker, and writes nothing but one JSON line on stdout:

- ``frames``, ``markers`` (poses solved), ``loop_wall_s``: its own wall time from before the video opened
  to the last frame done;
- ``decode_ms``, ``detect_ms``, ``pose_ms``, ``detect_pose_ms``: per-frame medians (and ``..._mean``) of
  PyAV's decode to a BGR array, grey conversion + ``detectMarkers``, the IPPE calls, and the last two
  together;
- with ``--ids``, ``ids``: the marker ids found in each frame, in decode order.
"""

from __future__ import annotations

import json
import sys
import time

__all__ = ["main"]


def main(argv: list[str]) -> int:
    """Run the loop over ``argv = [video, camera_yml, dictionary, marker_length_m]`` (and the flags
    ``--subpix``, ``--ids`` anywhere); print one JSON line."""
    import av
    import cv2
    import numpy as np

    subpix, with_ids = "--subpix" in argv, "--ids" in argv
    positional = [arg for arg in argv if arg not in ("--subpix", "--ids")]
    video, camera_yml, dictionary, length = positional[0], positional[1], positional[2], float(positional[3])
    storage = cv2.FileStorage(camera_yml, cv2.FILE_STORAGE_READ)
    k = storage.getNode("camera_matrix").mat()
    dist = storage.getNode("distortion_coefficients").mat()
    storage.release()
    parameters = cv2.aruco.DetectorParameters()
    if subpix:
        parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), parameters)
    h = length / 2.0
    square = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]], np.float32)
    start = time.perf_counter()
    markers = 0
    times: list[tuple[float, float, float, float]] = []
    ids_per_frame: list[list[int]] = []
    with av.open(video) as container:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        frames = container.decode(stream)
        while True:
            t0 = time.perf_counter()
            frame = next(frames, None)
            if frame is None:
                break
            image = frame.to_ndarray(format="bgr24")
            t1 = time.perf_counter()
            grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            corners, ids, _ = detector.detectMarkers(grey)
            t2 = time.perf_counter()
            for marker_corners in corners:
                count, _, _, _ = cv2.solvePnPGeneric(
                    square, marker_corners.reshape(4, 2), k, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE
                )
                markers += int(count > 0)
            t3 = time.perf_counter()
            times.append((t1 - t0, t2 - t1, t3 - t2, t3 - t1))
            ids_per_frame.append([] if ids is None else [int(i) for i in ids.reshape(-1)])
    wall = time.perf_counter() - start
    ms = np.asarray(times, dtype=np.float64).reshape(-1, 4) * 1e3
    stats: dict[str, float | None] = {}
    for column, name in enumerate(("decode_ms", "detect_ms", "pose_ms", "detect_pose_ms")):
        stats[name] = float(np.median(ms[:, column])) if len(ms) else None
        stats[name.replace("_ms", "_mean_ms")] = float(np.mean(ms[:, column])) if len(ms) else None
    result: dict[str, object] = {
        "frames": len(times),
        "markers": markers,
        "loop_wall_s": wall,
        "refine": "SUBPIX" if subpix else "NONE",
        **stats,
    }
    if with_ids:
        result["ids"] = ids_per_frame
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
