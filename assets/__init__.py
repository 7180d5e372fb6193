"""Models and data files: the FarmBot MJCF model (farmbot/)."""
