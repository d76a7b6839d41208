"""collabslam: collaborative SLAM and exploration for drone teams."""

__version__ = "0.1.0"
