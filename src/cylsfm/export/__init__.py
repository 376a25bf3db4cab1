"""Export of predictions: point clouds, meshes, stereo panoramas, viewer."""
