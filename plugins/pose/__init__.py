"""Pose estimator plugins (experimental): 6-DoF camera poses from virtual exposures."""
