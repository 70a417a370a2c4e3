"""Drawing on frames: the AR overlay, its 3D models, and the annotated video file."""
