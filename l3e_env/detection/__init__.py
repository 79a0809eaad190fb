"""Detectors behind one interface, and the one per-step localization pipeline."""
