"""Evaluation: depth metrics (Eigen et al.) and pose metrics (snippet ATE, full-trajectory APE/RPE).

- :mod:`.depth` and :mod:`.pose`: the two evaluations (protocols in their docstrings), their JSON
  layouts and printed tables; the public names of the modules below are re-exported there.
- :mod:`.depth_metrics` and :mod:`.pose_metrics`: the measures, as small functions and accumulators;
  :mod:`.motion`: the checks that tell a measured ego-motion from a prior (with the visual compass).
- :mod:`.depth_source` and :mod:`.pose_source`: where the scored depth and trajectories come from (a
  model, or stored predictions and trajectories).
- :mod:`.frames`: what both share (split frames, images as network input, read-ahead, yaw rolls, options).
- :mod:`.tables`: the one table formatter (text and Markdown); :mod:`.plots`: trajectory top views.
"""
