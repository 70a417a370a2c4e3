"""What a user needs around the tracker: printable marker sheets and camera calibration."""
