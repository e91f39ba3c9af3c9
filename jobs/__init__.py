"""Job directories: run, checkpoint, resume, lock, signals and Slurm submission."""
