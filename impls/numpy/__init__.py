"""numpy backend (CPU, float64/float32, no autodiff: analytic derivatives or finite differences)."""
