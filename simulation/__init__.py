"""collabslam simulation package."""
