"""User-facing outputs: the Gaussian map as PLY, PNG montages and trajectory plots, metrics JSON and summaries."""
