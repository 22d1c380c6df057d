"""SLAM: tracking, mapping, submaps, loop closure, pose graphs, refinement."""
