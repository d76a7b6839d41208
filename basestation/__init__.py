"""collabslam basestation package."""
