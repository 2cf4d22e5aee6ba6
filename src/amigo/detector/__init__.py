"""Detector models: linear geometry, the non-linear ramp (brighter-fatter) model, read-out."""
