"""collabslam protocol package."""
