"""Design: models, fractional calculus, tuning, the LMI, certificates, and the one pipeline config -> Design."""
