"""Semantic-aware loop detection (paper §III-C, Algorithm 1): descriptor database, Gaussian-IDF landmarks, detector."""
from gausem_core.slam.loop.database import DescriptorDatabase
from gausem_core.slam.loop.detector import LoopCandidate, LoopDetector, PlaceSignature, nearby_keyframes
from gausem_core.slam.loop.landmarks import gaussian_idf, landmark_distance, landmark_scores, observed_gaussians

__all__ = ["DescriptorDatabase", "LoopCandidate", "LoopDetector", "PlaceSignature", "gaussian_idf",
           "landmark_distance", "landmark_scores", "nearby_keyframes", "observed_gaussians"]
