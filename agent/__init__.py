"""collabslam agent package."""
