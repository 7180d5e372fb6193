"""What a job runs on and with: the evaluation's config tree, the run's description, plant sets
made into scored jobs, and the pollination task over them."""
