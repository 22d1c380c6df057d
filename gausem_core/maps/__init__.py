"""Maps derived from the Gaussian map for other consumers: the floor plane and a 2D occupancy grid."""
