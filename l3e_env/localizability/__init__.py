"""Registration, Monte-Carlo labels and the scan's own estimate (no torch)."""
