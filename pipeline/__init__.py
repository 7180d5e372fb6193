"""The field pipeline: point cloud to flower poses. Never imports sim, hardware or eval."""
