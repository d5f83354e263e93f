"""jax backend (CPU or GPU, float64 via ``jax_enable_x64``, autodiff, jit)."""
