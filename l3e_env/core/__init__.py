"""Poses and transforms, ordered worker processes, atomic file writes: used by every layer."""
