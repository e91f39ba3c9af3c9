"""What users take away from a run: PLY maps, trajectories, uncertainty images, metrics, reports."""
