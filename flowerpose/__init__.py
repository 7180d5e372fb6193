"""flowerpose: robotic 3D flower pose estimation, and a simulation-backed harness to score it."""
__version__ = "0.1.0"

#: The arguments of the command this process runs (`cli.main` sets it: a command called
#: from Python, e.g. a test, is not sys.argv's); reports record them.
invocation: list[str] | None = None
