"""cm3d: CogniMap3D in JAX. Importing it loads numpy and jax only (no OpenCV, Open3D, matplotlib)."""

__version__ = "0.1.0"
