"""Labelled datasets: sharded, resumable, deterministic; the Ray backend."""
