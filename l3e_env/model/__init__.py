"""The classifier: sparse convolution, networks, constraint layer, training, scores (torch here)."""
