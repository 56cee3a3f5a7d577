"""Reconstruction: unlabeled 2D blobs -> 3D points -> labeled marker trajectories.

- ``correspondence``: cross-camera matching of blobs by epipolar geometry, verified in the other
  cameras, and multi-view triangulation (all frames of a take at once);
- ``labeling``: marker identities from the rest take, followed frame to frame;
- ``trials``: trial averaging, noise floor and rejections;
- ``takes``: a take's and a session's reconstruction results.
"""
