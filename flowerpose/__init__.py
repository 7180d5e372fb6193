"""flowerpose: robotic 3D flower pose estimation, with a simulation-backed harness that scores it."""
__version__ = "0.1.0"
