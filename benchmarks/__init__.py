"""collabslam benchmarks package."""
