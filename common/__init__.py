"""collabslam common package."""
