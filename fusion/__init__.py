"""Estimation only (gtsam, filterpy, numpy): factor graph, EKF, localizability masks, ATE/RPE.

Imports nothing from the rest of the project.
"""
