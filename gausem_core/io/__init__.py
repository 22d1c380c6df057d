"""Files in and out: the Gaussian map as PLY, TUM trajectories, PNG montages and trajectory plots, metrics JSON and
summaries."""
