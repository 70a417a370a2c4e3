"""How a run reads, logs and records, beyond the tracker itself (:class:`RunOptions`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .stills import StillsPlan

__all__ = ["RunOptions"]


@dataclass(frozen=True)
class RunOptions:
    """How a run reads, logs and records, beyond the tracker itself.

    A source that declares a video file (:attr:`SourceInfo.video_path <ar_anchor.sources.base.SourceInfo>`)
    is referenced by the recording instead of its frames being logged as JPEG, when rerun can decode it.
    """

    max_frames: int | None = None
    spawn: bool = False
    connect: str | None = None  # a running rerun viewer's gRPC URL
    recording_name: str = "ar_anchor"
    recording_id: str | None = None  # shared with other processes: one recording (default: a new random id)
    camera_name: str | None = None  # this camera's entities under cameras/<name>/ (default: the tree unprefixed)
    record_raw: bool = False  # also write raw.mkv (lossless) + timestamps
    record_fps: float = 30.0
    video_out: Path | None = None  # write the annotated (overlay) video here
    images_out: StillsPlan | None = None  # write each image's annotated copy (an image folder's --images-out)
    overlays: bool = True  # the config's overlays (meshes in the recording; drawn for --video-out / overlay_images)
    decode_queue: int = 4  # frames decoded ahead of the tracker (file and synthetic sources)
    output_queue: int = 8  # tracked frames waiting for their overlay, video and rerun log
    recording: bool = True  # the rerun recording (False: --no-recording, poses.csv and summary.json only)
    output_process: bool = True  # draw and log in a process of its own (False: a thread of this process)
    extra_summary: dict[str, Any] = field(default_factory=dict)
