"""A video looped without re-encoding: its packets copied N times into a new container.

``ar-anchor bench speed`` loops chessboard.avi (149 frames) to over 1000 frames this way: the frames of
every copy decode to exactly the original's pixels (no generation loss), and the timestamps run on
(each copy's ``pts``/``dts`` shifted by the length of the copies before it), so the reader sees one long
clip at the original frame rate.
"""

from __future__ import annotations

import math
from pathlib import Path

__all__ = ["loop_video"]


def loop_video(source: Path, target: Path, min_frames: int) -> int:
    """Write ``target``: ``source``'s video stream repeated as many whole times as it takes to reach
    ``min_frames`` frames (at least once), packets copied with PyAV (``add_stream_from_template``) and
    their ``pts``/``dts`` renumbered; the frame count written (copies x the source's frames).

    Only the first video stream is copied (no audio). :class:`ValueError` for a source without video
    packets."""
    import av

    with av.open(str(source)) as reader:
        stream = reader.streams.video[0]
        packets = []
        for p in reader.demux(stream):
            if p.size:  # the demuxer's last packet of a stream is an empty flush packet: not a frame
                dts = p.dts if p.dts is not None else p.pts
                pts = p.pts if p.pts is not None else dts
                if pts is None or dts is None:
                    raise ValueError(f"{source}: a packet without timestamps")
                packets.append((pts, dts, p.duration or 1, p.is_keyframe, bytes(p)))
        time_base = stream.time_base
        if not packets:
            raise ValueError(f"{source}: no video packets")
        first = min(dts for _, dts, _, _, _ in packets)
        span = max(pts + duration for pts, _, duration, _, _ in packets) - first  # one copy's length (time_base)
        copies = max(1, math.ceil(min_frames / len(packets)))
        with av.open(str(target), "w") as writer:
            out = writer.add_stream_from_template(stream)
            for copy in range(copies):
                shift = copy * span - first
                for pts, dts, duration, keyframe, data in packets:
                    packet = av.Packet(data)
                    packet.pts = pts + shift
                    packet.dts = dts + shift
                    packet.duration = duration
                    packet.is_keyframe = keyframe
                    if time_base is not None:
                        packet.time_base = time_base
                    packet.stream = out
                    writer.mux(packet)
    return copies * len(packets)
