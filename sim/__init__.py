"""The synthetic world: procedural strawberry plants with exact ground truth."""
