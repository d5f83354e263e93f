"""torch backend (CPU or CUDA, float64/float32, reverse-mode autodiff)."""
