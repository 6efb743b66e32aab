"""Design: gradient PID tuning, batched gain grids and the losses they share."""
