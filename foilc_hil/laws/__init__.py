"""Learning laws: the per-sample update the trial loop calls."""
