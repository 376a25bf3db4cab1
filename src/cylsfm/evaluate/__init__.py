"""Evaluation: depth metrics (Eigen et al.) and pose metrics (snippet ATE, full-trajectory APE/RPE)."""
