"""flowerpose: robotic 3D flower pose estimation, and a simulation-backed harness to score it."""
__version__ = "0.1.0"
