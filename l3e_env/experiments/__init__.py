"""ATE, the tau sweep, Table III, judging real scans, the demo."""
