"""Regenerate the README's figures: ``python docs/make_figures.py`` (writes docs/images/)."""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from ar_anchor.camera import CameraModel
from ar_anchor.config import load_config
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import demo_scene
from ar_anchor.track.tracker import Tracker

OUT = Path(__file__).parent / "images"


def demo_frame(index: int = 40, frames: int = 300) -> np.ndarray:
    """A demo frame with detected outlines, ids and each marker's axes (from its output pose)."""
    config = load_config()
    camera = CameraModel.default_synthetic()
    source = SyntheticSource(demo_scene(config, camera, frames=frames))
    frame = source.frame(index)
    result = Tracker(config, camera).process(frame)
    image = frame.image.copy()
    for marker_id, corners in zip(result.detections.ids.tolist(), result.detections.corners):
        cv2.polylines(image, [np.round(corners * 16).astype(np.int32)], True, (60, 220, 60), 2, cv2.LINE_AA, shift=4)
        cv2.putText(
            image,
            str(marker_id),
            tuple(int(v) for v in corners[0] + (-4, -8)),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.7,
            (60, 220, 60),
            2,
            cv2.LINE_AA,
        )
    for target in result.targets.values():
        cv2.drawFrameAxes(
            image, camera.camera_matrix, None, target.pose.rvec, target.pose.tvec, target.length_m * 0.6, 2
        )
    return image


def demo_video_frame(index: int = 60) -> np.ndarray:
    """Frame ``index`` of ``ar-anchor demo --video-out demo.mp4`` (the annotated video), cropped to the targets."""
    with tempfile.TemporaryDirectory() as tmp:
        video = Path(tmp) / "demo.mp4"
        command = [sys.executable, "-m", "ar_anchor", "-q", "demo", "--max-frames", str(index + 1)]
        subprocess.run([*command, "--out", str(Path(tmp) / "run"), "--video-out", str(video)], check=True)
        capture = cv2.VideoCapture(str(video))
        for _ in range(index + 1):
            ok, image = capture.read()
            if not ok:
                raise SystemExit(f"{video}: has fewer than {index + 1} frames")
    return image[120:600, 280:1120]


if __name__ == "__main__":
    OUT.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(OUT / "demo_frame.jpg"), demo_frame(), [cv2.IMWRITE_JPEG_QUALITY, 85])
    cv2.imwrite(str(OUT / "demo_overlay.jpg"), demo_video_frame(), [cv2.IMWRITE_JPEG_QUALITY, 88])
    print(f"wrote {OUT / 'demo_frame.jpg'} and {OUT / 'demo_overlay.jpg'}")
