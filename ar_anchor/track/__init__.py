"""One frame's trip: detect markers, refine corners, solve both IPPE poses, filter them over time
(the planar flip) -> FrameResult. Nothing here draws, records or parses flags."""
