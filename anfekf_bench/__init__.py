"""anfekf-bench: Monte Carlo benchmark of the EKF against the adaptive neuro-fuzzy EKF (ANFEKF)."""

__version__ = "0.1.0"
