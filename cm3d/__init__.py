"""cm3d: CogniMap3D in JAX. Importing it loads numpy and jax only (no OpenCV, Open3D, matplotlib).

``cm3d.run(sequences, cfg=None, bank=None)`` is the one-call API (:func:`cm3d.pipeline.run`),
imported on first use so that ``import cm3d`` stays light.
"""

__version__ = "0.1.0"


def __getattr__(name):
    if name == "run":
        from cm3d.pipeline import run

        return run
    raise AttributeError(f"module 'cm3d' has no attribute {name!r}")
