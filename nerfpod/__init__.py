"""nerfpod: Neural Radiance Fields in JAX, from one CPU to a TPU pod."""
